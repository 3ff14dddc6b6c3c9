#!/usr/bin/env bash
# examples/ci run locally: the GitHub Actions and GitLab files parse and call the steps of
# examples/ci/lsnif-ci with the shard count they declare; then those steps, as the CI runs them:
# three shard processes at once into ONE shared cache directory, each as on another machine
# (1, 2 and 3 threads; LSNIF_ISA=avx2, avx512 and no cap), the merge with its JUnit report,
# compared with a single `lsnif batch` run byte for byte (manifest and every asset).
# The library has a malformed file: the shards go on, the merge reports it and exits 1.
# usage: ci_example.sh LSNIF_BINARY SOURCE_DIR MESH_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 src=$2 meshes=$3 scene=$4 work=$5
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/assets/props"
ci=$src/examples/ci/lsnif-ci

# The CI files: their structure, and that every step is a command of lsnif-ci.
python3 - "$src/examples/ci/github-actions.yml" "$src/examples/ci/gitlab-ci.yml" <<'PY' || bad "CI files"
import sys, yaml
gh = yaml.safe_load(open(sys.argv[1]))
jobs = gh["jobs"]
assert set(jobs) == {"build", "shard", "merge"}, set(jobs)
shards = int(gh["env"]["SHARDS"])
assert jobs["shard"]["strategy"]["matrix"]["shard"] == list(range(1, shards + 1))
runs = lambda job: " ".join(s.get("run", "") for s in jobs[job]["steps"])
uses = lambda job: [s.get("uses", "").split("@")[0] for s in jobs[job]["steps"]]
assert "lsnif-ci cache-key" in runs("build")
# Portable binaries: a -march=native build would die on runners of another CPU.
assert "cmake --preset tools" in runs("build") and "--preset release" not in runs("build"), runs("build")
assert "--threads" not in gh["env"]["LSNIF_OPTIONS"], gh["env"]
assert "lsnif-ci shard ${{ matrix.shard }} ${{ env.SHARDS }}" in runs("shard")
assert "lsnif-ci merge ${{ env.SHARDS }}" in runs("merge")
cache = [s for s in jobs["shard"]["steps"] if s.get("uses", "").startswith("actions/cache@")]
assert len(cache) == 1 and "needs.build.outputs.cache-key" in cache[0]["with"]["key"], cache
assert cache[0]["with"]["path"] == ".lsnif-cache"
assert "mikepenz/action-junit-report" in uses("merge") and jobs["merge"]["needs"] == ["build", "shard"]
gl = yaml.safe_load(open(sys.argv[2]))
assert gl["convert"]["parallel"] == int(gl["variables"]["SHARDS"])
assert 'lsnif-ci shard "$CI_NODE_INDEX" "$CI_NODE_TOTAL"' in " ".join(gl["convert"]["script"])
assert 'lsnif-ci merge "$SHARDS"' in " ".join(gl["merge"]["script"])
assert gl["merge"]["artifacts"]["reports"]["junit"] == "lsnif-out/junit.xml"
assert gl["convert"]["cache"]["paths"] == [".lsnif-cache"]
assert "cmake --preset tools" in " ".join(gl["build"]["script"]), gl["build"]["script"]
PY

# The library: CGAL meshes, the bundled scene, a malformed file.
cp "$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$work/assets/"
cp "$scene" "$work/assets/props/"
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\nnot a number\n3 0 1 2\n' >"$work/assets/broken.off"
cd "$work" || exit 1
export LSNIF=$lsnif LSNIF_LIBRARY=assets LSNIF_OPTIONS="--preset smoke --seed 3" \
  LSNIF_CACHE=.lsnif-cache LSNIF_OUT=lsnif-out

key=$("$ci" cache-key) || bad "cache-key exited $?"
[[ $key =~ ^lsnif-[0-9a-f]{32}$ && $key == "$("$ci" cache-key)" ]] || bad "cache-key: '$key'"

# Three shards at once, one shared cache directory (as on one runner, or a synced store), each
# with other threads and another instruction-set cap, as on a fleet of mixed runners (a cap
# above this CPU runs what the CPU has). --threads is not a setting: it may differ per job.
caps=(avx2 avx512 "")
pids=()
for i in 1 2 3; do
  LSNIF_ISA=${caps[$((i - 1))]} LSNIF_OPTIONS="$LSNIF_OPTIONS --threads $i" "$ci" shard "$i" 3 \
    >"shard$i.out" 2>"shard$i.err" &
  pids+=($!)
done
for i in 1 2 3; do
  wait "${pids[$((i - 1))]}" || bad "shard $i exited $?: $(tail -3 "shard$i.err")"
done
"$ci" merge 3 >merge.out 2>merge.err; rc=$?
[[ $rc == 1 ]] || bad "merge exited $rc (want 1: broken.off failed): $(cat merge.err)"
grep -q "1 failed assets" merge.out || bad "merge does not count the failure: $(cat merge.out)"
python3 - lsnif-out/junit.xml <<'PY' || bad "JUnit of the merge"
import sys, xml.etree.ElementTree as ET
suite = ET.parse(sys.argv[1]).getroot().find("testsuite")
cases = suite.findall("testcase")
assert int(suite.get("tests")) == len(cases) == 12, len(cases)  # 11 meshes + the broken input
failed = [c for c in cases if c.find("failure") is not None]
assert len(failed) == 1 and failed[0].get("classname").endswith("broken.off"), [c.get("classname") for c in failed]
assert not any("converted by shard" in (c.findtext("system-out") or "") for c in cases)
PY

# The same library on one machine, with a cache of its own: the same bytes (OUTDIR as deep as
# lsnif-out/library: the manifest records input paths relative to it).
"$lsnif" batch assets -o single/library --cache single-cache --preset smoke --threads 2 --seed 3 >/dev/null 2>&1
cmp -s lsnif-out/library/manifest.json single/library/manifest.json \
  || bad "merged manifest differs from the single run's: $(diff lsnif-out/library/manifest.json single/library/manifest.json | head -10)"
n=0
for f in single/library/*.lsnif; do
  n=$((n + 1))
  cmp -s "$f" "lsnif-out/library/$(basename "$f")" || bad "$(basename "$f") differs between the CI steps and one run"
done
((n >= 3)) || bad "the single run shipped $n assets"
# Every shard put its results into the one cache: a fourth run finds them all.
"$lsnif" batch assets -o warm --cache .lsnif-cache --preset smoke --threads 1 --seed 3 --json >warm.json 2>/dev/null
python3 -c "import json,sys; s=json.load(open(sys.argv[1])); assert s['cache']['stored'] == 0 and s['cache']['hits'] >= 3, s['cache']" \
  warm.json || bad "the shared cache does not hold every shard's results"
"$ci" shard 1 >/dev/null 2>&1; [[ $? == 2 ]] || bad "lsnif-ci shard without N: not a usage error"
exit $fail
