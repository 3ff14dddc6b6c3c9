#!/usr/bin/env bash
# Plan once: `lsnif batch --plan FILE` writes the library's plan; each `--from-plan FILE --task K`
# converts one object importing only its own input; `--shard I/N` a share of the tasks; the
# assembly (`--from-plan FILE` alone) writes the manifest from the cache, equal to a single
# `lsnif batch` run byte for byte. A changed input, another build's plan, settings given
# with a plan and bad task numbers are refused.
# usage: plan_once.sh LSNIF_BINARY MESH_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 meshes=$2 scene=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/lib/sub"
cp "$meshes/ChineseDragon-10kv.off" "$work/lib/"
cp "$meshes/armadillo.off" "$work/lib/sub/"
cp "$scene" "$work/lib/scene.glb"
lib=$work/lib
common=(--threads 2)

"$lsnif" batch "$lib" --plan "$work/plan.json" --preset smoke >"$work/plan.out" 2>"$work/plan.err" \
  || bad "plan: exit $? $(cat "$work/plan.err")"
grep -q "^planned  .* tasks (0 to .* - 1) over 3 inputs: $work/plan.json" "$work/plan.out" || bad "plan: $(cat "$work/plan.out")"
ntasks=$(python3 - "$work/plan.json" <<'PY'
import json, sys
p = json.load(open(sys.argv[1]))
assert p["format"] == "lsnif-plan/1", p["format"]
assert p["settings"][:2] == ["--preset", "smoke"], p["settings"]
assert len(p["inputs"]) == 3 and all(len(i["sha256"]) == 64 and i["path"].startswith("/") for i in p["inputs"])
costs = [t["estimated_ms"] for t in p["tasks"]]
assert costs == sorted(costs, reverse=True), costs
assert [t["task"] for t in p["tasks"]] == list(range(len(p["tasks"])))
assert len({t["key"] for t in p["tasks"]}) == len(p["tasks"])
print(len(p["tasks"]))
PY
) || bad "plan.json: $ntasks"
[[ $ntasks -ge 3 ]] || bad "plan: $ntasks tasks, want at least 3"

# One task per object: each imports its own input only and stores its entry.
for ((k = 0; k < ntasks; ++k)); do
  "$lsnif" batch --from-plan "$work/plan.json" --task $k -o "$work/tasks" --cache "$work/cache" "${common[@]}" \
    >"$work/task$k.out" 2>"$work/task$k.err" || bad "task $k: exit $? $(tail -3 "$work/task$k.err")"
  [[ $(grep -c ' import ' "$work/task$k.err") == 1 ]] || bad "task $k imported $(grep -c ' import ' "$work/task$k.err") inputs, not 1"
  key=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['tasks'][$k]['key'])" "$work/plan.json")
  [[ -f $work/cache/v1/entries/${key:0:2}/$key.entry ]] || bad "task $k: no cache entry for its key"
done
[[ $(find "$work/cache" -name '*.entry' | wc -l) == "$ntasks" ]] || bad "tasks: not one entry per task"
[[ -e $work/tasks/manifest.json ]] && bad "a task wrote a manifest"

# The assembly: everything from the cache, equal to a single run.
"$lsnif" batch --from-plan "$work/plan.json" -o "$work/assembled" --cache "$work/cache" "${common[@]}" --json \
  >"$work/assembled.json" 2>"$work/assembled.err" || bad "assembly: exit $? $(tail -3 "$work/assembled.err")"
python3 -c "import json,sys; s=json.load(open(sys.argv[1])); assert s['cache']['hits']==$ntasks and s['cache']['stored']==0, s['cache']" \
  "$work/assembled.json" || bad "assembly: not every task from the cache"
"$lsnif" batch "$lib" -o "$work/single" --cache "$work/single_cache" --preset smoke "${common[@]}" >/dev/null 2>&1 \
  || bad "single run: exit $?"
same() {  # same DIR: manifest and assets equal to the single run's
  cmp -s "$work/single/manifest.json" "$work/$1/manifest.json" || bad "$1: manifest differs from a single run's"
  for a in "$work/single"/*.lsnif; do cmp -s "$a" "$work/$1/$(basename "$a")" || bad "$1: $(basename "$a") differs"; done
}
same assembled

# Shards of the plan into another cache, then the assembly.
for i in 1 2; do
  "$lsnif" batch --from-plan "$work/plan.json" --shard $i/2 -o "$work/shards" --cache "$work/shard_cache" "${common[@]}" \
    >"$work/shard$i.out" 2>"$work/shard$i.err" || bad "shard $i/2: exit $?"
done
[[ $(find "$work/shard_cache" -name '*.entry' | wc -l) == "$ntasks" ]] || bad "shards: not every task stored once"
"$lsnif" batch --from-plan "$work/plan.json" -o "$work/shards_assembled" --cache "$work/shard_cache" "${common[@]}" \
  >/dev/null 2>&1 || bad "shards' assembly: exit $?"
same shards_assembled

# Refused: settings with a plan, task numbers, options that do not go together.
expect_usage() {  # expect_usage TEXT ARGS...: exit 2 with TEXT in the error
  local text=$1; shift
  "$lsnif" batch "$@" >"$work/usage.out" 2>"$work/usage.err"; local rc=$?
  [[ $rc == 2 ]] || bad "$*: exit $rc (want 2)"
  grep -q -- "$text" "$work/usage.err" || bad "$*: no '$text': $(cat "$work/usage.err")"
}
expect_usage "the plan fixes the settings, --preset" --from-plan "$work/plan.json" --task 0 -o "$work/x" --cache "$work/cache" --preset fast
expect_usage "--task $ntasks: the plan has $ntasks tasks" --from-plan "$work/plan.json" --task "$ntasks" -o "$work/x" --cache "$work/cache"
expect_usage "--task needs --from-plan" "$lib" --task 0 -o "$work/x" --cache "$work/cache"
expect_usage "the plan names the inputs" "$lib" --from-plan "$work/plan.json" -o "$work/x" --cache "$work/cache"
expect_usage "give one" "$lib" --plan "$work/p2.json" --ninja "$work/n.ninja" --cache "$work/cache"

# Another build's plan, and a file that is not a plan.
python3 - "$work/plan.json" "$work/other.json" <<'PY'
import json, sys
p = json.load(open(sys.argv[1])); p["tool"]["identity"] = "0" * 64
json.dump(p, open(sys.argv[2], "w"))
PY
"$lsnif" batch --from-plan "$work/other.json" --task 0 -o "$work/x" --cache "$work/cache" >/dev/null 2>"$work/other.err"
[[ $? == 1 ]] && grep -q "planned by another lsnif build.*plan again" "$work/other.err" || bad "another build's plan: $(cat "$work/other.err")"
python3 -c "import json,sys; p=json.load(open(sys.argv[1])); del p['tasks'][1]['key']; json.dump(p, open(sys.argv[2],'w'))" \
  "$work/plan.json" "$work/broken.json"
"$lsnif" batch --from-plan "$work/broken.json" --task 0 -o "$work/x" --cache "$work/cache" >/dev/null 2>"$work/broken.err"
[[ $? == 1 ]] && grep -q "broken.json: not an lsnif plan: tasks\[1\].key: missing" "$work/broken.err" || bad "broken plan: $(cat "$work/broken.err")"

# An input changed after planning: its tasks and the assembly are refused; other tasks run.
armadillo_task=$(python3 -c "
import json,sys; p=json.load(open(sys.argv[1]))
print(next(t['task'] for t in p['tasks'] if p['inputs'][t['input']]['path'].endswith('armadillo.off')))" "$work/plan.json")
other_task=$(python3 -c "
import json,sys; p=json.load(open(sys.argv[1]))
print(next(t['task'] for t in p['tasks'] if not p['inputs'][t['input']]['path'].endswith('armadillo.off')))" "$work/plan.json")
echo "# edited" >>"$lib/sub/armadillo.off"
"$lsnif" batch --from-plan "$work/plan.json" --task "$armadillo_task" -o "$work/x" --cache "$work/cache" >/dev/null 2>"$work/changed.err"
[[ $? == 1 ]] && grep -q "armadillo.off: changed since it was planned in .*plan.json: plan again" "$work/changed.err" \
  || bad "changed input: $(cat "$work/changed.err")"
"$lsnif" batch --from-plan "$work/plan.json" --task "$other_task" -o "$work/x" --cache "$work/cache" >/dev/null 2>&1 \
  || bad "a task of an unchanged input refused after another input changed"
"$lsnif" batch --from-plan "$work/plan.json" -o "$work/x" --cache "$work/cache" >/dev/null 2>"$work/changed_all.err"
[[ $? == 1 ]] && grep -q "plan again" "$work/changed_all.err" || bad "assembly after a change: $(cat "$work/changed_all.err")"

[[ $fail == 0 ]] && echo "PASS: plan once"
exit $fail
