#!/usr/bin/env bash
# scripts/convert-scene on the bundled example scene: every output written, every asset valid,
# and report.html loaded in Debian's chromium (headless): every image decoded, no script error,
# every object named on the page; a screenshot is left in the work directory for people to
# look at. Then: a malformed scene (exit 1, an error line) and usage errors (exit 2).
# Needs chromium (scripts/setup --browser, which scripts/test runs).
# usage: convert_scene.sh LSNIF_BINARY SOURCE_DIR EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 src=$2 scene=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work"
browser=$(command -v chromium || true)
[[ -n $browser ]] || { echo "FAIL: chromium is not installed (scripts/setup --browser)"; exit 1; }
export LSNIF=$lsnif  # convert-scene uses this build instead of building its own

"$src/scripts/convert-scene" "$scene" "$work/out" --preview 160x120 -- --preset smoke --threads 2 --seed 3 \
  >"$work/stdout" 2>"$work/stderr"; rc=$?
[[ $rc == 0 ]] || bad "convert-scene exited $rc: $(tail -5 "$work/stderr")"
for f in manifest.json scene.gltf scene.bin convert.json validate.json eval/report.json report.html; do
  [[ -s $work/out/$f ]] || bad "no $f"
done
grep -q "^report: $work/out/report.html" "$work/stdout" || bad "no report line: $(tail -3 "$work/stdout")"
grep -q "objects, 11 instances" "$work/stdout" || bad "no summary line"
python3 -c "import json,sys; d=json.load(open(sys.argv[1])); assert d['valid'] and d['files']" \
  "$work/out/validate.json" || bad "validate.json does not say every asset is valid"

# The page in a real browser: the page's own load check (scripts/scene_report) marks <body>.
page="file://$work/out/report.html"
chrome=("$browser" --headless --no-sandbox --disable-gpu --hide-scrollbars --user-data-dir="$work/chrome")
"${chrome[@]}" --dump-dom "$page" >"$work/dom.html" 2>"$work/chrome.err" || bad "chromium exited $?"
body=$(grep -o '<body[^>]*>' "$work/dom.html")
[[ $body =~ data-images=\"ok\ ([0-9]+)\" ]] || bad "images not all loaded: $body"
(( ${BASH_REMATCH[1]:-0} == 9 )) || bad "the page has ${BASH_REMATCH[1]:-0} images (want 9: 3 effects x reference, hybrid, FLIP)"
[[ $body != *data-errors* ]] || bad "script errors on the page: $body"
python3 - "$work/out/manifest.json" "$work/dom.html" <<'PY' || bad "the page does not name every object"
import html, json, sys
names = [m["name"] for m in json.load(open(sys.argv[1]))["meshes"]]
page = html.unescape(open(sys.argv[2]).read())
missing = [n for n in names if f"<td>{n}</td>" not in page]
assert not missing, missing
PY
"${chrome[@]}" --window-size=1300,2200 --screenshot="$work/report.png" "$page" >/dev/null 2>&1
[[ -s $work/report.png ]] || bad "no screenshot"

# A page that cannot load an image says so (the check itself can fail).
sed 's/src="data:image\/png;base64,/src="data:image\/png;base64,AAAA/' "$work/out/report.html" >"$work/out/broken.html"
"${chrome[@]}" --dump-dom "file://$work/out/broken.html" 2>/dev/null | grep -q 'data-images="missing: ' \
  || bad "a page with broken images passed the check"

# Bad input: a malformed scene fails with an error line; usage errors exit 2.
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\nnot a number\n3 0 1 2\n' >"$work/broken.off"
"$src/scripts/convert-scene" "$work/broken.off" "$work/bad" >"$work/bad.out" 2>"$work/bad.err"; rc=$?
[[ $rc == 1 ]] || bad "malformed scene: exit $rc"
grep -q "broken.off" "$work/bad.err" "$work/bad.out" || bad "malformed scene: no error naming the file"
"$src/scripts/convert-scene" "$work/none.glb" "$work/none" >/dev/null 2>&1; rc=$?
[[ $rc == 2 ]] || bad "missing scene: exit $rc"
"$src/scripts/convert-scene" "$scene" "$work/x" --preview big >/dev/null 2>&1; rc=$?
[[ $rc == 2 ]] || bad "--preview big: exit $rc"
exit $fail
