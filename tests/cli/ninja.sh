#!/usr/bin/env bash
# `lsnif batch --ninja FILE` and Ninja itself: one edge per unique object in a pool of depth 1,
# the library step writing the same manifest as `lsnif batch`; nothing runs again when nothing
# changed; a touched input re-runs its objects once (cache hits) and is then clean; a changed
# mesh converts exactly that object; a malformed file fails the library step alone; usage
# errors. Needs ninja (ninja-build, installed by scripts/setup).
# usage: ninja.sh LSNIF_BINARY MESH_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 meshes=$2 scene=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/lib"
cp "$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$scene" "$work/lib/"
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\nnot a number\n3 0 1 2\n' >"$work/lib/broken.off"
settings=(--preset smoke --threads 2 --seed 3)
file=$work/build/lib.ninja
# Edges that ran, by description, from a Ninja log (progress lines "[k/n] lsnif: MESH (INPUT)").
ran() { grep -o '^\[[0-9]*/[0-9]*\] lsnif: .*' "$1" | sed 's/^\[[0-9/]*\] lsnif: //' | sort; }

# Planned with relative paths, as a user types them (the file's steps use absolute ones).
(cd "$work" && "$lsnif" batch lib -o out --cache cache "${settings[@]}" --ninja build/lib.ninja \
  >"$work/plan.out" 2>"$work/plan.err"); rc=$?
[[ $rc == 0 ]] || bad "plan exited $rc: $(cat "$work/plan.err")"
grep -q "broken.off.*the library step will fail on it" "$work/plan.err" || bad "plan does not warn about broken.off"
objects=$(grep -c '^build .*\.entry: object ' "$file")
[[ $objects == 4 ]] || bad "the plan has $objects object edges (want 4: two CGAL meshes, the scene's dragon and hairball)"
grep -q 'depth = 1' <<<"$(grep -A1 '^pool convert$' "$file")" || bad "no pool of depth 1"

# Cold: every object once, then the library step, which fails on broken.off alone (-k 0).
ninja -f "$file" -k 0 >"$work/cold.log" 2>&1; rc=$?
[[ $rc != 0 ]] || bad "ninja succeeded although broken.off cannot be read"
[[ $(ran "$work/cold.log" | grep -c ' (') == 4 ]] || bad "cold run: $(ran "$work/cold.log" | tr '\n' ';')"
grep -q "FAILED: .*out/manifest.json" "$work/cold.log" || bad "the library step did not fail"
grep -q "^failed   .*broken.off" "$work/cold.log" || bad "broken.off is not the failure"
# The library step's manifest equals a plain lsnif batch run of the same library and settings.
"$lsnif" batch "$work/lib" -o "$work/plain" --cache "$work/plain_cache" "${settings[@]}" >/dev/null 2>&1
cmp -s "$work/out/manifest.json" "$work/plain/manifest.json" \
  || bad "Ninja's manifest differs from lsnif batch's: $(diff "$work/out/manifest.json" "$work/plain/manifest.json" | head -10)"
n=$(ls "$work/plain"/*.lsnif | wc -l)
[[ $n == 3 && $(ls "$work/out"/*.lsnif | wc -l) == 3 ]] || bad "assets: $n plain, $(ls "$work/out"/*.lsnif | wc -l) Ninja"

# Without the malformed file, nothing is left to do; a touched input re-runs its objects once.
rm "$work/lib/broken.off"
ninja -f "$file" >"$work/second.log" 2>&1 || bad "second run failed: $(tail -5 "$work/second.log")"
[[ -z $(ran "$work/second.log" | grep ' (') ]] || bad "second run converted: $(ran "$work/second.log" | tr '\n' ';')"
ninja -f "$file" >"$work/third.log" 2>&1
grep -q "no work to do" "$work/third.log" || bad "third run did work: $(cat "$work/third.log" | head -5)"
sleep 0.01 && touch "$work/lib/armadillo.off"
ninja -f "$file" -d explain >"$work/touch.log" 2>&1 || bad "touched run failed"
[[ $(ran "$work/touch.log" | grep ' (') == "armadillo ("*")" ]] || bad "touched run: $(ran "$work/touch.log" | tr '\n' ';')"
grep -q "cache: 1 found, 0 stored" "$work/touch.log" || bad "the touched object was not a cache hit"
grep -q "ninja explain: .*armadillo.off" "$work/touch.log" || bad "-d explain does not name the touched input"
ninja -f "$file" >"$work/after_touch.log" 2>&1
grep -q "no work to do" "$work/after_touch.log" || bad "dirty after a touch: $(head -5 "$work/after_touch.log")"

# One changed mesh: Ninja plans again and converts exactly that object.
python3 - "$work/lib/ChineseDragon-10kv.off" <<'PY'
import sys
lines = open(sys.argv[1]).read().split("\n")
x, y, z = lines[2].split()[:3]
lines[2] = f"{float(x) * 1.001} {y} {z}"
open(sys.argv[1], "w").write("\n".join(lines))
PY
ninja -f "$file" >"$work/changed.log" 2>&1 || bad "changed run failed: $(tail -5 "$work/changed.log")"
grep -q "plan the library again" "$work/changed.log" || bad "Ninja did not plan again"
[[ $(ran "$work/changed.log" | grep ' (') == "ChineseDragon-10kv ("*")" ]] \
  || bad "changed run: $(ran "$work/changed.log" | tr '\n' ';')"
grep -q "cache: 0 found, 1 stored" "$work/changed.log" || bad "the changed mesh was not converted"

# Every setting that changes a result reaches the steps: a plan made with the flags added last
# (the settings table drives both the plan's keys and the steps' arguments) converts, where a
# step that computed another key would fail with "plan again".
mkdir -p "$work/one" && cp "$meshes/armadillo.off" "$work/one/"
"$lsnif" batch "$work/one" -o "$work/flags_out" --cache "$work/flags_cache" "${settings[@]}" --keep-inactive \
  --no-give-up --fixed-model --steps 30 --ninja "$work/flags.ninja" >/dev/null 2>"$work/flags_plan.err" \
  || bad "plan with flags: $(cat "$work/flags_plan.err")"
for f in --keep-inactive --no-give-up --fixed-model; do
  grep -q -- "^settings = .*$f" "$work/flags.ninja" || bad "the steps do not pass $f: $(grep settings "$work/flags.ninja")"
done
ninja -f "$work/flags.ninja" >"$work/flags.log" 2>&1 || bad "the flagged plan's steps failed: $(tail -5 "$work/flags.log")"

# Usage errors, and a step whose key is not in the plan.
"$lsnif" batch "$work/lib" -o "$work/out" --cache "$work/cache" --ninja "$work/x.ninja" --shard 1/2 2>"$work/err"; rc=$?
[[ $rc == 2 ]] && grep -q "cannot be combined" "$work/err" || bad "--ninja --shard: exit $rc $(cat "$work/err")"
"$lsnif" batch "$work/lib" -o "$work/lib/out" --cache "$work/cache" --ninja "$work/x.ninja" 2>"$work/err"; rc=$?
[[ $rc == 2 ]] && grep -q "inside the input directory" "$work/err" || bad "OUTDIR inside an input: exit $rc $(cat "$work/err")"
[[ ! -e $work/x.ninja ]] || bad "a refused plan wrote its file"
"$lsnif" batch "$work/lib/armadillo.off" --object 0000 -o "$work/out" --cache "$work/cache" "${settings[@]}" \
  >/dev/null 2>"$work/err"; rc=$?
[[ $rc == 1 ]] && grep -q "no candidate of the inputs has this cache key" "$work/err" || bad "--object unknown: exit $rc"
exit $fail
