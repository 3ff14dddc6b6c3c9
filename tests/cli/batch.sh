#!/usr/bin/env bash
# `lsnif batch` on a small library as CI runs it: directories, list files and a malformed
# file; JUnit XML; the exit codes; a warm run converts nothing; one changed mesh converts
# exactly that mesh; a deleted input leaves the manifest.
# usage: batch.sh LSNIF_BINARY MESH_DIR WORK_DIR
set -uo pipefail
lsnif=$1 meshes=$2 work=$3
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/lib/sub" "$work/empty"
cp "$meshes/ChineseDragon-10kv.off" "$work/lib/"
cp "$meshes/armadillo.off" "$work/lib/sub/"
head -c 3000 /usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb >"$work/lib/broken.glb"
echo "not a scene" >"$work/lib/notes.txt.md"
run() {  # run NAME ARGS...: lsnif batch into $work/out with the shared cache; sets rc
  local name=$1; shift
  "$lsnif" batch "$@" -o "$work/out" --cache "$work/cache" --preset smoke --threads 2 --json \
    --junit "$work/$name.xml" >"$work/$name.json" 2>"$work/$name.err"; rc=$?
}
summary() {  # summary NAME EXPR: a Python expression on the --json summary `s` must hold
  python3 -c "import json,sys; s=json.load(open(sys.argv[1])); assert $2, s" "$work/$1.json" >/dev/null 2>&1 \
    || bad "$1: $2 does not hold: $(head -c 600 "$work/$1.json")"
}

# Cold: the directory is searched (notes.txt.md ignored); the malformed file fails alone.
run cold "$work/lib"; [[ $rc == 1 ]] || bad "cold: exit $rc (want 1: one input failed)"
summary cold 's["assets"] == {"lsnif": 2, "bvh": 0, "failed": 1}'
summary cold 's["cache"]["stored"] == 2 and s["cache"]["hits"] == 0'
python3 - "$work/cold.xml" <<'PY' || bad "cold JUnit XML"
import sys, xml.etree.ElementTree as ET
root = ET.parse(sys.argv[1]).getroot()
assert root.tag == "testsuites", root.tag
suite = root.find("testsuite")
cases = suite.findall("testcase")
assert int(suite.get("tests")) == len(cases) == 3, len(cases)
assert int(suite.get("failures")) == 1
for c in cases:
    assert c.get("name") and c.get("classname") and float(c.get("time")) >= 0
failed = [c for c in cases if c.find("failure") is not None]
assert len(failed) == 1 and failed[0].get("classname").endswith("broken.glb"), failed
assert "invalid binary glTF" in failed[0].find("failure").get("message")
PY

# Without --json: each asset's line once (streamed as it finishes), the failed input's, the count.
"$lsnif" batch "$work/lib" -o "$work/out" --cache "$work/cache" --preset smoke --threads 2 >"$work/text.out" 2>/dev/null
[[ $(grep -c "^lsnif    " "$work/text.out") == 2 ]] || bad "text lines: $(cat "$work/text.out")"
[[ $(grep -c "^failed   .*broken.glb" "$work/text.out") == 1 ]] || bad "failed line: $(cat "$work/text.out")"
[[ $(tail -1 "$work/text.out") == "2 LSNIF, 0 BVH, 1 failed; cache: 2 found, 0 stored, 0 corrupt" ]] \
  || bad "count line: $(tail -1 "$work/text.out")"

# Warm, through a list file naming the directory's files (and a comment): nothing converts.
printf '# the library\nChineseDragon-10kv.off\n\nsub/armadillo.off\nbroken.glb\n' >"$work/lib/library.list"
run warm "$work/lib/library.list"; [[ $rc == 1 ]] || bad "warm: exit $rc"
summary warm 's["cache"]["hits"] == 2 and s["cache"]["stored"] == 0'

# One mesh changed (one coordinate of the armadillo): exactly that mesh converts.
python3 - "$work/lib/sub/armadillo.off" <<'PY'
import sys
lines = open(sys.argv[1]).read().split("\n")
i = next(k for k, l in enumerate(lines) if len(l.split()) == 3 and k > 1)
x = lines[i].split(); x[0] = repr(float(x[0]) + 1e-3); lines[i] = " ".join(x)
open(sys.argv[1], "w").write("\n".join(lines))
PY
rm "$work/lib/broken.glb"
run changed "$work/lib/ChineseDragon-10kv.off" "$work/lib/sub"; [[ $rc == 0 ]] || bad "changed: exit $rc"
summary changed 's["cache"]["hits"] == 1 and s["cache"]["stored"] == 1'
summary changed 's["assets"] == {"lsnif": 2, "bvh": 0, "failed": 0}'

# A deleted input leaves the manifest.
rm "$work/lib/ChineseDragon-10kv.off"
run deleted "$work/lib"; [[ $rc == 0 ]] || bad "deleted: exit $rc"
python3 -c "
import json, sys
m = json.load(open(sys.argv[1]))
names = [x['name'] for x in m['meshes']]
assert names == ['armadillo'], names" "$work/out/manifest.json" || bad "deleted input still in the manifest"

# An assembly: assimp's 2CylinderEngine (29 meshes, 67 instances; short training), cold then
# warm: the warm run converts nothing and writes the same manifest.
engine=/usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb
for k in cold warm; do
  "$lsnif" batch "$engine" -o "$work/engine_$k" --cache "$work/engine_cache" --preset smoke --threads 2 --steps 40 \
    --json >"$work/engine_$k.json" 2>/dev/null || bad "engine $k: exit $?"
done
summary engine_cold 's["cache"]["stored"] >= 10 and s["assets"]["failed"] == 0'
summary engine_warm 's["cache"]["stored"] == 0 and s["cache"]["hits"] >= 10'
cmp -s "$work/engine_cold/manifest.json" "$work/engine_warm/manifest.json" || bad "engine: warm manifest differs"
python3 -c "import json,sys; m=json.load(open(sys.argv[1])); assert len(m['meshes']) == 29 and len(m['instances']) == 67" \
  "$work/engine_warm/manifest.json" || bad "engine: not 29 meshes and 67 instances"

# A repeated setting takes one value per occurrence: the directory after `--complex NAME` is an
# input, wherever it stands (the dry runs plan the library and print a line per mesh).
for order in before after; do
  if [[ $order == before ]]; then
    args=("$work/lib" --complex armadillo --complex bunny)
  else
    args=(--complex armadillo "$work/lib")
  fi
  "$lsnif" batch "${args[@]}" -o "$work/order_$order" --cache "$work/cache" --preset smoke --dry-run \
    >"$work/order_$order.out" 2>"$work/order_$order.err"; rc=$?
  [[ $rc == 0 ]] && grep -q "armadillo" "$work/order_$order.out" \
    || bad "--complex with the input $order: exit $rc $(cat "$work/order_$order.err" "$work/order_$order.out" | head -5)"
done

# Inputs that name nothing: a failure naming them, exit 1. Usage errors: exit 2.
run nothing "$work/empty" "$work/missing.off"; [[ $rc == 1 ]] || bad "nothing: exit $rc"
grep -q "empty: no scene files" "$work/nothing.err" || bad "empty directory not reported: $(cat "$work/nothing.err")"
grep -q "missing.off: no such file" "$work/nothing.err" || bad "missing input not reported"
"$lsnif" batch "$work/lib" -o "$work/out" 2>/dev/null; rc=$?
[[ $rc == 2 ]] || bad "batch without --cache: exit $rc (want 2)"
"$lsnif" batch "$work/lib" -o "$work/out" --cache "$work/cache" --target 120,1,15 2>/dev/null; rc=$?
[[ $rc == 2 ]] || bad "batch --target 120: exit $rc (want 2)"
exit $fail
