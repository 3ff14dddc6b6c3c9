#!/usr/bin/env bash
# End to end as processes: convert CGAL's dragon (smoke preset), then `lsnif eval`,
# `lsnif bench memory` and the reference renderer examples/render on the result.
# usage: eval_render.sh LSNIF_BINARY RENDER_BINARY MESH WORK_DIR
set -uo pipefail
lsnif=$1 render=$2 mesh=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work"
out=$work/conv

"$lsnif" convert "$mesh" -o "$out" --preset smoke --complex ChineseDragon-10kv --threads 2 --seed 5 >/dev/null 2>&1 \
  || { echo "FAIL: convert exited $?"; exit 1; }
ls "$out"/*.lsnif >/dev/null 2>&1 || bad "no asset written"
# Same command into another directory (and with --json): byte-identical asset.
"$lsnif" convert "$mesh" --json -o "$work/again" --preset smoke --complex ChineseDragon-10kv --threads 2 --seed 5 \
  >/dev/null 2>&1 || bad "second convert exited $?"
for f in "$out"/*.lsnif; do
  cmp -s "$f" "$work/again/$(basename "$f")" || bad "$(basename "$f") differs between two identical conversions"
done

# eval: text report, the nine PNGs and report.json; JSON flavour parses and has FLIP in [0,1].
txt=$("$lsnif" eval "$out" --width 64 --height 48 --ao-samples 2 --images "$work/img") || bad "eval exited $?"
grep -q "overall    FLIP mean" <<<"$txt" || bad "eval text lacks the overall line: $txt"
for kind in reference hybrid flip; do
  for effect in shadow ao reflection; do
    f=$work/img/${kind}_${effect}.png
    [[ $(head -c 8 "$f" | od -An -tx1 | tr -d ' \n') == 89504e470d0a1a0a ]] || bad "$f is not a PNG"
  done
done
[[ -s $work/img/report.json ]] || bad "no report.json"
"$lsnif" eval "$out" --width 32 --height 24 --ao-samples 1 --repeats 2 --images "$work/img2" --json >"$work/eval.json" || bad "eval --json exited $?"
python3 - "$work/eval.json" <<'PY' || bad "eval JSON"
import json, sys
r = json.load(open(sys.argv[1]))
assert r["lsnif_instances"] == 1, r
assert r["timing_repeats"] == 2, r
assert r["embree_route"] == "packets16", r
for e in ("shadow", "ao", "reflection"):
    assert 0.0 <= r["images"][e]["flip_mean"] <= 1.0
PY
# Embree one ray per call: reported, and the same comparison (Embree's packet and single-ray
# kernels may decide a grazing ray differently, so not byte for byte); an unknown route is a
# usage error.
"$lsnif" eval "$out" --width 32 --height 24 --ao-samples 1 --repeats 2 --images "$work/img6" --embree-route single \
  --json >"$work/single.json" || bad "--embree-route single exited $?"
python3 - "$work/eval.json" "$work/single.json" <<'PY' || bad "--embree-route single report"
import json, sys
packets, single = (json.load(open(f)) for f in sys.argv[1:])
assert single["embree_route"] == "single", single
assert abs(single["flip_mean"] - packets["flip_mean"]) < 0.005, (single["flip_mean"], packets["flip_mean"])
PY
"$lsnif" eval "$out" --embree-route wide --images "$work/img7" 2>"$work/err"; rc=$?
[[ $rc == 2 ]] || bad "--embree-route wide exit $rc"
grep -q "^error: --embree-route" "$work/err" || bad "--embree-route wide message: $(cat "$work/err")"
[[ ! -e $work/img7 ]] || bad "--embree-route wide still rendered"
# No timing at all is a usage error (exit 2), nothing rendered.
"$lsnif" eval "$out" --repeats 0 --images "$work/img4" 2>"$work/err"; rc=$?
[[ $rc == 2 ]] || bad "--repeats 0 exit $rc"
grep -q "^error: --repeats" "$work/err" || bad "--repeats 0 message: $(cat "$work/err")"
[[ ! -e $work/img4 ]] || bad "--repeats 0 still rendered"
# The earlier name still works, with a warning.
"$lsnif" eval "$out" --width 16 --height 12 --ao-samples 1 --timing-repeats 1 --images "$work/img5" --json \
  >"$work/old.json" 2>"$work/old.err" || bad "--timing-repeats exited $?"
grep -q "^warning: --timing-repeats is deprecated" "$work/old.err" || bad "no deprecation warning: $(cat "$work/old.err")"
python3 -c "import json,sys; assert json.load(open(sys.argv[1]))['timing_repeats'] == 1" "$work/old.json" \
  || bad "--timing-repeats 1 not applied"
# Bad camera string: usage error (exit 2), one error line, nothing rendered.
"$lsnif" eval "$out" --camera 1,2,x --images "$work/img3" 2>"$work/err"; rc=$?
[[ $rc == 2 ]] || bad "bad --camera exit $rc"
grep -q "^error: --camera" "$work/err" || bad "bad --camera message: $(cat "$work/err")"
[[ ! -e $work/img3 ]] || bad "bad --camera still rendered"
# Bad --target values: usage errors (exit 2) naming the option, no output directory.
for t in 120,1,15 97,-1,15 97,1,200 97,1 x,1,15 97,1,15,3; do
  "$lsnif" convert "$mesh" -o "$work/target_$t" --preset smoke --target "$t" 2>"$work/err"; rc=$?
  [[ $rc == 2 ]] || bad "--target $t: exit $rc"
  grep -q "^error: --target '$t'" "$work/err" || bad "--target $t message: $(cat "$work/err")"
  [[ ! -e $work/target_$t ]] || bad "--target $t still wrote output"
done
# Bad --memory-budget values: usage errors (exit 2) naming the option, no output directory.
for b in 0 -5 abc 12x 1.5.2 '' 99999999999T; do
  "$lsnif" convert "$mesh" -o "$work/budget_bad" --preset smoke --memory-budget "$b" 2>"$work/err"; rc=$?
  [[ $rc == 2 ]] || bad "--memory-budget '$b': exit $rc"
  grep -q "^error: --memory-budget '$b'" "$work/err" || bad "--memory-budget '$b' message: $(cat "$work/err")"
  [[ ! -e $work/budget_bad ]] || bad "--memory-budget '$b' still wrote output"
done
# A budget the dragon's BVH already fits: nothing converted, the report shows the scene's
# memory, exit 0. A budget it cannot reach: a warning, still exit 0.
"$lsnif" convert "$mesh" -o "$work/budget_fits" --preset smoke --memory-budget 1G >"$work/out" 2>"$work/err" \
  || bad "--memory-budget 1G: exit $?"
grep -q "fits the memory budget without it" "$work/out" || bad "--memory-budget 1G report: $(cat "$work/out")"
grep -q "^scene memory (each mesh once; Embree BVHs, assets as held in memory): .* budget 1.00 GiB: fits" "$work/out" || bad "scene memory line: $(cat "$work/out")"
ls "$work/budget_fits"/*.lsnif >/dev/null 2>&1 && bad "--memory-budget 1G converted the dragon"
"$lsnif" convert "$mesh" -o "$work/budget_over" --preset smoke --complex ChineseDragon-10kv --memory-budget 1K \
  --dry-run >"$work/out" 2>"$work/err" || bad "--memory-budget 1K: exit $?"
grep -q "^warning: the scene needs .* over the memory budget of 1024 bytes" "$work/err" \
  || bad "--memory-budget 1K warning: $(cat "$work/err")"
# A budget below what stays BVH in any case (here the dragon, forced simple): exit 2.
"$lsnif" convert "$mesh" -o "$work/budget_low" --preset smoke --simple ChineseDragon-10kv --memory-budget 1K \
  >"$work/out" 2>"$work/err"; rc=$?
[[ $rc == 2 ]] || bad "--memory-budget below the simple geometry: exit $rc"
grep -q "^error: --memory-budget 1024 bytes is below the BVHs" "$work/err" || bad "low budget message: $(cat "$work/err")"
[[ ! -e $work/budget_low ]] || bad "low budget still wrote output"
# Missing conversion: exit 1 naming manifest.json.
"$lsnif" eval "$work/nothing" 2>"$work/err"; rc=$?
[[ $rc == 1 ]] && grep -q "manifest.json" "$work/err" || bad "missing OUTDIR: exit $rc, $(cat "$work/err")"

# bench memory names the object and both byte counts.
grep -q "ChineseDragon-10kv *19994" <<<"$("$lsnif" bench memory "$out")" || bad "bench memory output"

# bench infer reports every stage of the inference pass with a positive rate.
"$lsnif" bench infer --threads 1 --seconds 0.01 --json >"$work/infer.json" || bad "bench infer exited $?"
python3 - "$work/infer.json" <<'PY' || bad "bench infer stages"
import json, sys
st = json.load(open(sys.argv[1]))["stages"]
keys = ["walk_scalar_rays_per_second", "walk_rays_per_second", "walk_encode_rays_per_second"]
assert all(st[k] > 0 for k in keys), st
assert st["walk_encode_rays_per_second"] < st["walk_rays_per_second"], st  # encoding adds work
PY

# The reference renderer: a P6 image of the requested size, not all background, and the
# asset opened with the escape rule its metadata names (docs/model.md "The escape rule").
"$render" "$out" "$work/r.ppm" 64 48 >"$work/render.out" || bad "render exited $?"
escaping=$(python3 -c "import json, sys; m = json.load(open(sys.argv[1]))
print(sum(1 for x in m['meshes'] if 'lsnif' in x and x['metrics'].get('escape_points', 0) > 0))" "$out/manifest.json")
grep -q ", $escaping of 1 with the escape rule;" "$work/render.out" ||
  bad "render: expected $escaping of 1 assets with the escape rule: $(cat "$work/render.out")"
head -c 13 "$work/r.ppm" | cmp -s - <(printf 'P6\n64 48\n255\n') || bad "render header"
[[ $(stat -c %s "$work/r.ppm") == $((13 + 64 * 48 * 3)) ]] || bad "render size"
distinct=$(tail -c $((64 * 48 * 3)) "$work/r.ppm" | od -An -tu1 -v | tr -s ' ' '\n' | sort -u | wc -l)
(( distinct > 10 )) || bad "render looks empty ($distinct distinct byte values)"
exit $fail
