#!/usr/bin/env bash
# `lsnif batch --shard I/N` on three machines (three processes, each with its own cache), then
# `lsnif merge`: the manifest and every asset equal a single run's, byte for byte. Incomplete
# or repeated shard sets, and shards of another arithmetic or lsnif identity, are refused; bad
# --shard values are usage errors (that -j 2 equals one job is tests/cli/same_bytes.sh's case).
# usage: shard.sh LSNIF_BINARY MESH_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 meshes=$2 scene=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work"
same_outputs() {  # DIR_A DIR_B WHAT: the same manifest and the same assets, byte for byte
  cmp -s "$1/manifest.json" "$2/manifest.json" \
    || bad "$3: the manifests differ: $(diff "$1/manifest.json" "$2/manifest.json" | head -20)"
  local n=0 f
  for f in "$2"/*.lsnif; do
    n=$((n + 1))
    cmp -s "$f" "$1/$(basename "$f")" || bad "$3: $(basename "$f") differs"
  done
  ((n >= 2)) || bad "$3: $2 has $n assets"
}
inputs=("$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$scene")
settings=(--preset smoke --threads 2 --seed 3)

for i in 1 2 3; do
  "$lsnif" batch "${inputs[@]}" -o "$work/shard$i" --cache "$work/cache$i" --shard "$i/3" "${settings[@]}" \
    >"$work/shard$i.out" 2>"$work/shard$i.err" || bad "shard $i/3 exited $?: $(cat "$work/shard$i.err")"
done
# Every candidate is converted by exactly one shard.
python3 - "$work" <<'PY' || bad "shards do not split the candidates"
import json, sys
docs = [json.load(open(f"{sys.argv[1]}/shard{i}/manifest.json")) for i in (1, 2, 3)]
owners = {}
for k, d in enumerate(docs, start=1):
    assert d["shard"] == {"index": k, "count": 3}, d["shard"]
    for m in d["meshes"]:
        if "shard" in m:
            owners.setdefault(m["id"], set()).add(m["shard"])
            assert (m["shard"] == k) == (not m["reasons"][-1].startswith("converted by shard")), m
assert len(owners) >= 3 and all(len(v) == 1 for v in owners.values()), owners
assert len({next(iter(v)) for v in owners.values()}) == 3, owners  # every shard has work
PY
"$lsnif" merge "$work/shard1" "$work/shard2" "$work/shard3" -o "$work/merged" --json >"$work/merge.json" \
  2>"$work/merge.err" || bad "merge exited $?: $(cat "$work/merge.err")"
python3 -c "
import json, sys
s = json.load(open(sys.argv[1]))
assert s['errors'] == [] and s['meshes'] >= 3 and s['manifest'].endswith('merged/manifest.json'), s
m = json.load(open(s['manifest']))
assert s['scene_memory'] == m['scene_memory'] and s['scene_memory']['after'] > 0, (s, m['scene_memory'])" "$work/merge.json" \
  || bad "merge --json: $(cat "$work/merge.json")"
"$lsnif" batch "${inputs[@]}" -o "$work/single" --cache "$work/cache_single" "${settings[@]}" >/dev/null 2>&1 \
  || bad "single run exited $?"
same_outputs "$work/merged" "$work/single" "merged shards against a single run"

"$lsnif" batch "${inputs[0]}" -o "$work/u" --cache "$work/cache1" -j 2 --memory-budget 1M 2>"$work/err"; rc=$?
[[ $rc == 2 ]] && grep -q "jobs and --memory-budget" "$work/err" || bad "-j with --memory-budget: exit $rc"

# Refused: an incomplete set, a repeated shard, shards of different settings.
"$lsnif" merge "$work/shard1" "$work/shard2" -o "$work/m2" 2>"$work/err"; rc=$?
[[ $rc == 1 ]] && grep -q "does not complete a set of 2 shards" "$work/err" || bad "incomplete set: exit $rc $(cat "$work/err")"
"$lsnif" merge "$work/shard1" "$work/shard1" "$work/shard3" -o "$work/m3" 2>"$work/err"; rc=$?
[[ $rc == 1 ]] || bad "repeated shard: exit $rc"
[[ ! -e $work/m2/manifest.json && ! -e $work/m3/manifest.json ]] || bad "a refused merge wrote a manifest"
# Shards of another arithmetic or of another lsnif are refused, naming the field that differs
# (shards of other thread counts and CPUs are not: tests/cli/ci_example.sh).
for field in settings.arithmetic tool.identity; do
  rm -rf "$work/other3" && cp -r "$work/shard3" "$work/other3"
  python3 - "$work/other3/manifest.json" "$field" <<'PY'
import json, sys
path, field = sys.argv[1], sys.argv[2]
doc = json.load(open(path))
obj, key = field.split(".")
doc[obj][key] = "machine-bf16/amx" if key == "arithmetic" else "0" * 64
json.dump(doc, open(path, "w"), indent=2)
PY
  "$lsnif" merge "$work/shard1" "$work/shard2" "$work/other3" -o "$work/m5" 2>"$work/err"; rc=$?
  [[ $rc == 1 ]] && grep -q "$field is " "$work/err" || bad "a shard of another $field: exit $rc $(cat "$work/err")"
  [[ ! -e $work/m5/manifest.json ]] || bad "a refused merge (another $field) wrote a manifest"
done
"$lsnif" merge "$work/single" -o "$work/m4" 2>"$work/err"; rc=$?
[[ $rc == 1 ]] && grep -q "not written by lsnif batch --shard" "$work/err" || bad "unsharded input: exit $rc"
# Usage errors.
for s in 0/3 4/3 3 a/b 1/0 2/1; do
  "$lsnif" batch "${inputs[0]}" -o "$work/u" --cache "$work/cache1" --shard "$s" 2>"$work/err"; rc=$?
  [[ $rc == 2 ]] && grep -q "^error: --shard '$s'" "$work/err" || bad "--shard $s: exit $rc $(cat "$work/err")"
done
"$lsnif" batch "${inputs[0]}" -o "$work/u" --cache "$work/cache1" --shard 1/2 --memory-budget 1M 2>"$work/err"; rc=$?
[[ $rc == 2 ]] || bad "--shard with --memory-budget: exit $rc"
exit $fail
