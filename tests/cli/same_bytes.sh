#!/usr/bin/env bash
# The same input gives the same bytes on any machine (docs/pipeline.md "The same bytes
# everywhere"). CGAL's dragon, converted by `lsnif batch` (whose manifest has no timings) with
# a short training run that ships whatever it learned, each run with a cache of its own:
#   threads     --threads 2 is the reference; --threads 1, 3 and 5 write the same asset,
#               manifest and cache entry; three meshes with -j 2 equal one job, two of
#               them the same geometry under two names (the first in input order owns the
#               asset, whichever job finishes first).
#   isa CAP     LSNIF_ISA=CAP (generic, avx2) writes the reference's bytes; a cap above this
#               CPU exits 77 (CTest: skipped), naming what is missing, and so does the cap at
#               this CPU's own level, the reference's path (avx2 on a CPU without AVX-512).
#               Higher caps are no other path of the canonical arithmetic: avx512 is an
#               AVX-512 CPU's own level, avx512bf16 and amx change only the machine
#               arithmetic (mode machine).
#   machine     --arithmetic machine: on a CPU with bf16 products the manifest, metadata and
#               key name the instructions and the asset differs; capped below them
#               (LSNIF_ISA=avx512) it is the canonical arithmetic, the reference's bytes.
#   ladder      the sizing ladder's other paths, at 2 and 3 threads: a target met early (training
#               stops at it; a smaller table is tried and given up when its curve falls
#               behind) on the dragon, and a target no coarse grid reaches (the grid rung
#               trains again on a finer grid) on CGAL's armadillo with the smoke preset.
#   reference   the --threads 2 run the others compare with (WORK_ROOT/reference), made first.
# usage: same_bytes.sh LSNIF MESH_DIR WORK_ROOT reference|threads|machine|ladder|isa CAP
set -uo pipefail
. "$(dirname "$0")/../skip.sh"
lsnif=$1 meshes=$2 root=$3 mode=$4 cap=${5:-}
fail=0
bad() { echo "FAIL: $*"; fail=1; }
settings=(--preset fast --steps 120 --gate-visibility 0 --seed 4 --complex ChineseDragon-10kv)
mkdir -p "$root"

# convert NAME [ENV=VALUE...] -- [lsnif batch options...]: the dragon into $root/NAME.
convert() {
  local name=$1
  shift
  local envs=()
  while [[ $1 != -- ]]; do envs+=("$1"); shift; done
  shift
  rm -rf "$root/$name" "$root/$name.cache"
  env "${envs[@]}" "$lsnif" batch "$meshes/ChineseDragon-10kv.off" -o "$root/$name" --cache "$root/$name.cache" \
    "${settings[@]}" "$@" >"$root/$name.log" 2>&1 || bad "$name: exit $?: $(tail -3 "$root/$name.log")"
}

# same A B WHAT: the assets, manifests and cache entries of two runs are the same bytes.
same() {
  local a=$root/$1 b=$root/$2 n=0
  for f in "$a"/*.lsnif; do
    n=$((n + 1))
    cmp -s "$f" "$b/$(basename "$f")" || bad "$3: $(basename "$f") differs"
  done
  ((n >= 1)) || bad "$3: $1 shipped no asset"
  cmp -s "$a/manifest.json" "$b/manifest.json" ||
    bad "$3: manifests differ: $(diff "$a/manifest.json" "$b/manifest.json" | head -6)"
  (cd "$a.cache" && find . -type f | sort | xargs sha256sum) >"$b.entries_a"
  (cd "$b.cache" && find . -type f | sort | xargs sha256sum) >"$b.entries_b"
  cmp -s "$b.entries_a" "$b.entries_b" || bad "$3: cache entries differ"
}

# The reference: made by mode "reference" (CTest's fixture, first), read by the others.
if [[ $mode == reference ]]; then
  rm -rf "$root" && mkdir -p "$root"
  convert reference -- --threads 2
  exit $fail
fi
[[ -d $root/reference && -d $root/reference.cache ]] || { echo "FAIL: no reference in $root (run mode reference first)"; exit 1; }

# What this CPU lacks for a cap or for bf16 products (tests/isa_required.sh).
missing_for() { "$(dirname "$0")/../isa_required.sh" --missing "$1"; }

case $mode in
  threads)
    for t in 1 3 5; do
      convert "threads$t" -- --threads "$t"
      same reference "threads$t" "--threads $t against --threads 2"
    done
    # Three meshes at once (-j 2, one thread each) against one job of two threads; the last
    # is the dragon again under another name.
    mkdir -p "$root/copy" && cp "$meshes/ChineseDragon-10kv.off" "$root/copy/dragon_copy.off"
    for j in 1 2; do
      rm -rf "$root/jobs$j" "$root/jobs$j.cache"
      "$lsnif" batch "$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$root/copy/dragon_copy.off" \
        -o "$root/jobs$j" --cache "$root/jobs$j.cache" "${settings[@]}" --complex armadillo \
        --complex dragon_copy --threads 2 -j "$j" \
        >"$root/jobs$j.log" 2>&1 || bad "-j $j: exit $?: $(tail -3 "$root/jobs$j.log")"
    done
    same jobs1 jobs2 "-j 2 against -j 1"
    python3 - "$root/jobs2/manifest.json" <<'PY' || bad "the copy does not share the dragon's asset"
import json, sys
m = {x["name"]: x for x in json.load(open(sys.argv[1]))["meshes"]}
dragon, copy = m["ChineseDragon-10kv"], m["dragon_copy"]
assert copy["lsnif"]["file"] == dragon["lsnif"]["file"], (copy["lsnif"], dragon["lsnif"])
assert "as mesh 'ChineseDragon-10kv'" in copy["reasons"][-1], copy["reasons"]
PY
    grep -q '"name": "ChineseDragon-10kv"' <<<"$("$lsnif" inspect "$root/jobs2/$(python3 -c "
import json, sys
print([x for x in json.load(open(sys.argv[1]))['meshes'] if x['name'] == 'dragon_copy'][0]['lsnif']['file'])" \
      "$root/jobs2/manifest.json")")" || bad "the shared asset does not name the first input's mesh"
    ;;
  isa)
    why=$(missing_for "$cap") || exit 2
    [[ -z $why ]] || skip_or_fail "$cap" "LSNIF_ISA=$cap: this CPU lacks $why"
    # The canonical arithmetic uses nothing above AVX-512 (bf16 products and AMX are the
    # machine arithmetic's): a cap at this CPU's own level of it runs the reference's path.
    top=avx2
    [[ -n $(missing_for avx512) ]] || top=avx512
    if [[ $cap == "$top" ]]; then
      echo "SKIP: LSNIF_ISA=$cap is this CPU's own level for the canonical arithmetic: the reference ran this path"
      exit 77
    fi
    convert "isa_$cap" LSNIF_ISA="$cap" -- --threads 2
    same reference "isa_$cap" "LSNIF_ISA=$cap against no cap"
    ;;
  machine)
    convert machine -- --threads 2 --arithmetic machine
    id=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['settings']['arithmetic'])" \
      "$root/machine/manifest.json")
    if [[ -z $(missing_for avx512bf16) ]]; then
      [[ $id == machine-bf16/* ]] || bad "--arithmetic machine on a bf16 CPU recorded '$id'"
      grep -q "\"arithmetic\": \"$id\"" <<<"$("$lsnif" inspect "$root"/machine/*.lsnif)" || bad "the asset does not say $id"
      [[ $(ls "$root/machine.cache"/v1/entries/*/) != $(ls "$root/reference.cache"/v1/entries/*/) ]] ||
        bad "the machine arithmetic has the canonical cache key"
      cmp -s "$root"/machine/*.lsnif "$root"/reference/*.lsnif && bad "bf16 training wrote the canonical asset"
    else
      echo "no AVX-512 BF16 here: --arithmetic machine is the canonical arithmetic"
      [[ $id == canonical-* ]] || bad "--arithmetic machine without bf16 recorded '$id'"
    fi
    # Below the bf16 instructions, the machine arithmetic is the canonical one.
    convert machine_capped LSNIF_ISA=avx512 -- --threads 2 --arithmetic machine
    same reference machine_capped "--arithmetic machine under LSNIF_ISA=avx512 against canonical"
    ;;
  ladder)
    # ladder NAME MESH THREADS SETTINGS...: MESH into $root/ladder_NAME_THREADS.
    ladder() {
      local name=$1 mesh=$2 threads=$3 out=$root/ladder_$1_$3
      shift 3
      rm -rf "$out" "$out.cache"
      "$lsnif" batch "$meshes/$mesh" -o "$out" --cache "$out.cache" --seed 4 --gate-visibility 0 --threads "$threads" \
        "$@" >"$out.log" 2>&1 || bad "ladder $name, $threads threads: exit $?: $(tail -3 "$out.log")"
    }
    # A target met early: training stops at it, and a smaller table is tried and given up
    # when its curve falls behind the larger one's.
    for t in 2 3; do
      ladder down ChineseDragon-10kv.off "$t" --preset fast --steps 200 --target 90,8,45 --complex ChineseDragon-10kv
    done
    same ladder_down_2 ladder_down_3 "stopped at the target, smaller table: --threads 3 against 2"
    python3 - "$root/ladder_down_2/manifest.json" <<'PY' || bad "the dragon did not go down the ladder"
import json, sys
c = json.load(open(sys.argv[1]))["meshes"][0]["candidates"]
sizes = {x["log2_table_size"] for x in c}
assert len(sizes) >= 2, c
assert any(x.get("stopped") == "the validation curve met the target" for x in c), c
assert any(x.get("stopped", "").startswith("given up") for x in c if x["log2_table_size"] == min(sizes)), c
PY
    # A target no 16^3 grid reaches: the grid rung trains again at 32^3.
    for t in 2 3; do
      ladder grid armadillo.off "$t" --preset smoke --steps 200 --batch 8192 --target 100,8,45 --max-grid 32 \
        --complex armadillo
    done
    same ladder_grid_2 ladder_grid_3 "finer grid: --threads 3 against 2"
    python3 - "$root/ladder_grid_2/manifest.json" <<'PY' || bad "the armadillo was not trained on a finer grid"
import json, sys
m = json.load(open(sys.argv[1]))["meshes"][0]
assert any("trained again at 32^3" in r for r in m["reasons"]), m["reasons"]
assert {x["grid_resolution"] for x in m["candidates"]} == {32}, m["candidates"]
PY
    ;;
  *)
    echo "usage: same_bytes.sh LSNIF MESH_DIR WORK_ROOT reference|threads|machine|ladder|isa CAP" >&2
    exit 2
    ;;
esac
exit $fail
