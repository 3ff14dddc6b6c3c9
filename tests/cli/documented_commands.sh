#!/usr/bin/env bash
# Every command and script the README and the docs show a user, run briefly on real data:
# the README's lsnif lines, scripts/demo, the fuzzers for a few seconds each, and every
# measuring script on its smallest input (one scene, one setting, the smoke preset), each
# checked for the files it promises. A documented command that no longer builds or runs
# fails here. Slow (minutes): label "documented", run by scripts/test in the release tree.
# usage: documented_commands.sh LSNIF_BINARY PROJECT_DIR BUILD_DIR MESH_DIR WORK_DIR
set -uo pipefail
lsnif=$1 project=$2 build=$3 meshes=$4 work=$5
rm -rf "$work" && mkdir -p "$work"
failures=0
# step NAME COMMAND...: runs COMMAND (output in WORK/NAME.log), reports PASS or FAIL with its tail.
step() {
    local name=$1
    shift
    local t0=$SECONDS rc=0
    "$@" >"$work/$name.log" 2>&1 || rc=$?
    if ((rc == 0)); then
        echo "PASS: $name ($((SECONDS - t0)) s)"
        return 0
    fi
    echo "FAIL: $name: exit $rc ($*)"
    tail -15 "$work/$name.log" | sed 's/^/    /'
    failures=$((failures + 1))
    return 1
}
# expect NAME FILE...: every FILE exists and is not empty.
expect() {
    local name=$1
    shift
    for f in "$@"; do
        [[ -s $f ]] || { echo "FAIL: $name wrote no $f"; failures=$((failures + 1)); }
    done
}
dragon=$meshes/ChineseDragon-10kv.off
cp "$dragon" "$work/statue.off"

# README "Convert your own scene": the four lsnif lines, on a real mesh and a small library.
mkdir -p "$work/assets"
cp "$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off" "$work/assets/"
step readme_convert "$lsnif" convert "$work/statue.off" -o "$work/out" --preset smoke &&
    expect readme_convert "$work/out/manifest.json" "$work/out/scene.gltf"
step readme_batch "$lsnif" batch "$work/assets" -o "$work/lib" --cache "$work/cache" -j 2 --preset smoke &&
    expect readme_batch "$work/lib/manifest.json"
step readme_eval "$lsnif" eval "$work/out" --width 64 --height 48 --images "$work/out/eval" &&
    expect readme_eval "$work/out/eval/report.json"
shopt -s nullglob
assets=("$work"/out/*.lsnif)
shopt -u nullglob
if ((${#assets[@]} > 0)); then
    step readme_validate "$lsnif" validate "${assets[@]}"
    step readme_inspect "$lsnif" inspect "${assets[0]}"
else
    echo "FAIL: readme_convert made no asset to validate"
    failures=$((failures + 1))
fi
step readme_version "$lsnif" --version
step readme_man man -l "$build/converter/lsnif.1.gz"

# README's first command, with the fast preset (the default one is the accuracy tests' job).
step demo bash "$project/scripts/demo" fast && expect demo "$project/build/demo/report.html"
step convert_scene bash "$project/scripts/convert-scene" "$work/statue.off" "$work/scene_out" --preview 96x72 \
    -- --preset smoke && expect convert_scene "$work/scene_out/report.html"

# CONTRIBUTING "Fuzz": both targets build and run.
step fuzz_reader bash "$project/scripts/fuzz" reader 5
step fuzz_import bash "$project/scripts/fuzz" import 5

# The measuring scripts (BENCHMARKS.md "Running the benchmarks"), each on its smallest input.
step tradeoff "$project/scripts/tradeoff" --lsnif "$lsnif" --mesh "$dragon" --only fast --out "$work/tradeoff" &&
    expect tradeoff "$work/tradeoff/tradeoff.csv" "$work/tradeoff/tradeoff_time.svg" "$work/tradeoff/tradeoff_bytes.svg"
grep -q "commit" "$work/tradeoff/tradeoff_time.svg" 2>/dev/null ||
    { echo "FAIL: tradeoff_time.svg does not state the commit it measured"; failures=$((failures + 1)); }
step bench_table "$project/scripts/bench_table" --build "$build" --only 2 --preset smoke --out "$work/bench_table" \
    --work "$work/bench_table_work" && expect bench_table "$work/bench_table/bench_table.md"
step eval_scenes "$project/scripts/eval_scenes" --build "$build" --only statues --preset smoke \
    --out "$work/eval_scenes" --work "$work/eval_scenes_work" &&
    expect eval_scenes "$work/eval_scenes/eval_scenes.md" "$work/eval_scenes/eval_scenes/statues_flip_combined.png"
step sizing_chart "$project/scripts/sizing_chart" --build "$build" --only "CGAL bunny00" --preset smoke \
    --sweep 16 --budgets 1M --out "$work/sizing" --work "$work/sizing_work" &&
    expect sizing_chart "$work/sizing/sizing.md" "$work/sizing/sizing_chart.svg"
step failure_modes "$project/scripts/failure_modes" --build "$build" --only blob --preset smoke \
    --out "$work/failure_modes" --work "$work/failure_modes_work" &&
    expect failure_modes "$work/failure_modes/failure_modes.json" "$work/failure_modes_work/failure_modes_table.md"
step calibrate_image_gate "$project/scripts/calibrate_image_gate" --build "$build" --only "CGAL homer" \
    --preset smoke --target 50,20,90 --out "$work/image_gate" --work "$work/image_gate_work" &&
    expect calibrate_image_gate "$work/image_gate/image_gate.json" "$work/image_gate/image_gate.md"
step seed_sweep "$project/scripts/seed_sweep" --build "$build" --mesh "$dragon" --seeds 2 --preset smoke \
    --out "$work/seed_sweep" --work "$work/seed_sweep_work" && expect seed_sweep "$work/seed_sweep/seed_sweep.json"

# docs/packaging.md "Python": the example as printed, on a conformance asset, with the
# module of this build (scripts/setup --charts installs matplotlib).
python_example() {
    local code
    code=$(awk '/^## Python/ {in_section = 1} in_section && /^```python/ {grab = 1; next}
                grab && /^```/ {exit} grab {print}' "$project/docs/packaging.md")
    [[ -n $code ]] || { echo "no python block under docs/packaging.md ## Python"; return 1; }
    (cd "$work" && cp "$project/schema/conformance/peterbilt_fp16.lsnif" dragon.lsnif &&
        MPLBACKEND=Agg PYTHONPATH="$build/format/python/module" /usr/bin/python3 -c "$code")
}
step python_example python_example && expect python_example "$work/slice.png"

if ((failures > 0)); then
    echo "FAIL: $failures documented commands failed"
    exit 1
fi
echo "PASS: every documented command ran"
