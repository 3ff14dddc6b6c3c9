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
"${chrome[@]}" --window-size=1300,2200 --dump-dom "$page" >"$work/dom.html" 2>"$work/chrome.err" || bad "chromium exited $?"
body=$(grep -o '<body[^>]*>' "$work/dom.html")
[[ $body =~ data-images=\"ok\ ([0-9]+)\" ]] || bad "images not all loaded: $body"
images=${BASH_REMATCH[1]:-0}
objects=$(python3 -c "import json,sys; print(len(json.load(open(sys.argv[1]))['objects']))" "$work/out/eval/objects.json")
((objects >= 1)) || bad "no converted object close up (eval/objects.json)"
# The scene's 3 effects and each converted object's 3 views, each as reference, hybrid, FLIP;
# and the scene's all-neural combined image with its FLIP.
((images == 11 + 9 * objects)) || bad "the page has $images images (want $((11 + 9 * objects)))"
[[ $body != *data-errors* ]] || bad "script errors on the page: $body"
python3 - "$work/out/manifest.json" "$work/dom.html" "$work/out/eval/objects.json" <<'PY' || bad "the page does not show every object as it should"
import html, json, re, sys
meshes = json.load(open(sys.argv[1]))["meshes"]
page = html.unescape(open(sys.argv[2]).read())
objects = json.load(open(sys.argv[3]))["objects"]
# Every object named: in a row of its own, or (too small to weigh) in the folded line.
small = [m["name"] for m in meshes if m["decision"] == "few_triangles"]
rows = [m["name"] for m in meshes if m["decision"] != "few_triangles"]
missing = [n for n in rows if f"<td>{n}</td>" not in page]
assert not missing, missing
folded = re.search(r"(\d+) small objects .*?</summary>(.*?)</details>", page, re.S)
assert folded and int(folded.group(1)) == len(small), small
assert all(n in folded.group(2) for n in small), (small, folded.group(2))
# Converted objects first, and every one close up.
classes = re.findall(r'<tr class="(complex|simple|failed)">', page)
assert classes and classes[0] == "complex" and classes.index("simple") > classes.count("complex") - 1, classes
shipped = {m["name"] for m in meshes if "lsnif" in m}
assert {o["name"] for o in objects} == shipped, (objects, shipped)
assert all(f'alt="{n} view 0 hybrid"' in page for n in shipped)
# The scene's own name in the title, not a build path.
assert "<title>lsnif: example_scene.glb</title>" in page, re.search("<title>.*</title>", page)
# Each converted object large enough to see: its close-ups at least 240 CSS pixels wide as laid
# out in a 1300-pixel window (the renders are 160 pixels wide, shown twice that).
width = re.search(r'data-closeup-min-width="(\d+)"', page)
assert width and int(width.group(1)) >= 240, width and width.group(0)
PY
"${chrome[@]}" --window-size=1300,2200 --screenshot="$work/report.png" "$page" >/dev/null 2>&1
[[ -s $work/report.png ]] || bad "no screenshot"

# A page that cannot load an image says so (the check itself can fail).
sed 's/src="data:image\/png;base64,/src="data:image\/png;base64,AAAA/' "$work/out/report.html" >"$work/out/broken.html"
"${chrome[@]}" --dump-dom "file://$work/out/broken.html" >"$work/broken.dom" 2>/dev/null || true
grep -q 'data-images="missing: ' "$work/broken.dom" || bad "a page with broken images passed the check"

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
