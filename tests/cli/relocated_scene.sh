#!/usr/bin/env bash
# A converted scene works from anywhere (manifest format lsnif-manifest/4): convert the
# bundled example scene (simple meshes, two LSNIF meshes, instances) with a relative input
# path, then render it with examples/render and `lsnif eval` from other working
# directories and after moving the whole project. Also: a view where every primary ray
# misses, inputs that are gone, an older manifest format and a damaged manifest — each a
# clear one-line error (exit 1) and no output file, never an abort.
# usage: relocated_scene.sh LSNIF_BINARY RENDER_BINARY EXAMPLE_SCENE_GLB WORK_DIR
set -uo pipefail
lsnif=$1 render=$2 scene=$3 work=$4
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/proj/src" "$work/elsewhere"
work=$(cd "$work" && pwd)
cp "$scene" "$work/proj/src/scene.glb"

# Converted from the project directory with a relative input path, as a user types it.
(cd "$work/proj" && "$lsnif" convert src/scene.glb -o out --preset smoke --gate-visibility 0 --threads 2 --seed 3 \
  >/dev/null 2>&1) || { echo "FAIL: convert exited $?"; exit 1; }
python3 - "$work/proj/out/manifest.json" <<'PY' || bad "manifest inputs"
import json, sys
m = json.load(open(sys.argv[1]))
assert m["format"] == "lsnif-manifest/4", m["format"]
i = m["inputs"][0]
assert i["path"] == "../src/scene.glb", i  # relative to the manifest's own directory
assert i["given"] == "src/scene.glb", i    # as typed, for humans
complex_meshes = [x for x in m["meshes"] if x["class"] == "complex" and "lsnif" in x]
assert len(complex_meshes) == 2, [x["class"] for x in m["meshes"]]
PY

# The reference renderer from the project directory and from an unrelated one: same image.
(cd "$work/proj" && "$render" out "$work/a.ppm" 96 72 >/dev/null) || bad "render from the project exited $?"
(cd "$work/elsewhere" && "$render" ../proj/out "$work/b.ppm" 96 72 >/dev/null) || bad "render from elsewhere exited $?"
cmp -s "$work/a.ppm" "$work/b.ppm" || bad "renders from two working directories differ"
distinct=$(tail -c $((96 * 72 * 3)) "$work/a.ppm" | od -An -tu1 -v | tr -s ' ' '\n' | sort -u | wc -l)
(( distinct > 20 )) || bad "render looks empty ($distinct distinct byte values)"
# The same scene through OUT/scene.gltf (schema/LSNIF_neural_geometry.md): the same image. With
# one tagged mesh's geometry hash altered, that mesh is traced as triangles, with a warning.
(cd "$work/elsewhere" && "$render" ../proj/out/scene.gltf "$work/g.ppm" 96 72 >/dev/null) \
  || bad "render of scene.gltf exited $?"
cmp -s "$work/a.ppm" "$work/g.ppm" || bad "the render of scene.gltf differs from the manifest's"
# The assets as Embree user geometries (lsnif_embree.h), single rays and packets: the image
# of the batched route, byte for byte (both answer each asset for the whole ray). --packet
# alone or with another width is a usage error.
for packet in 1 4 8 16; do
  "$render" "$work/proj/out" "$work/u$packet.ppm" 96 72 --user-geometry --packet $packet >"$work/u.out" ||
    bad "render --user-geometry --packet $packet exited $?"
  grep -q "assets traced Embree user geometry, $packet-ray calls" "$work/u.out" || bad "user-geometry report: $(cat "$work/u.out")"
  cmp -s "$work/a.ppm" "$work/u$packet.ppm" || bad "the user-geometry render (packets of $packet) differs from the batched one"
done
for args in "--packet 4" "--user-geometry --packet 3"; do
  "$render" "$work/proj/out" "$work/p.ppm" 96 72 $args >/dev/null 2>&1; rc=$?
  [[ $rc == 2 && ! -e $work/p.ppm ]] || bad "render $args: exit $rc (usage error expected, no image)"
done
python3 - "$work/proj/out/scene.gltf" "$work/proj/out/stale.gltf" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
tagged = [m for m in d["meshes"] if "LSNIF_neural_geometry" in m.get("extensions", {})]
assert len(tagged) == 2, len(tagged)
tagged[0]["extensions"]["LSNIF_neural_geometry"]["geometryHash"] = "fnv1a64:0000000000000000"
json.dump(d, open(sys.argv[2], "w"))
PY
"$render" "$work/proj/out/stale.gltf" "$work/s.ppm" 96 72 >/dev/null 2>"$work/stale.err" || bad "stale glTF exited $?"
grep -q "changed since it was converted: tracing its triangles" "$work/stale.err" || bad "no warning for a stale hash"

# lsnif eval from elsewhere: all four LSNIF instances traced, FLIP in range.
eval_json() { # OUTDIR IMAGES JSON_OUT [extra...]
  local o=$1 i=$2 j=$3
  shift 3
  "$lsnif" eval "$o" --width 48 --height 36 --ao-samples 1 --threads 2 --images "$i" --json "$@" >"$j"
}
(cd "$work/elsewhere" && eval_json ../proj/out img e1.json) || bad "eval from elsewhere exited $?"
python3 - "$work/elsewhere/e1.json" <<'PY' || bad "eval report"
import json, sys
r = json.load(open(sys.argv[1]))
assert r["lsnif_instances"] == 4, r["lsnif_instances"]
for e in ("shadow", "ao", "reflection"):
    assert 0.0 <= r["images"][e]["flip_mean"] <= 1.0, r["images"][e]
PY

# Move the whole project (sources and OUTDIR keep their relative layout): still the same image.
mv "$work/proj" "$work/moved"
(cd "$work/moved/out" && "$render" . "$work/c.ppm" 96 72 >/dev/null) || bad "render after the move exited $?"
cmp -s "$work/a.ppm" "$work/c.ppm" || bad "render after moving the project differs"
(cd / && eval_json "$work/moved/out" "$work/img2" "$work/e2.json") || bad "eval after the move exited $?"
"$lsnif" bench memory "$work/moved/out" >/dev/null || bad "bench memory after the move exited $?"

# A view where every primary ray misses: every pixel is the background, nothing aborts.
"$render" "$work/moved/out" "$work/miss.ppm" 32 24 --camera 0,50,0,0,60,0 >/dev/null || bad "all-miss render exited $?"
distinct=$(tail -c $((32 * 24 * 3)) "$work/miss.ppm" | od -An -tu1 -v | tr -s ' ' '\n' | sed '/^$/d' | sort -u | wc -l)
(( distinct == 1 )) || bad "all-miss render is not uniform ($distinct distinct byte values)"
eval_json "$work/moved/out" "$work/img3" "$work/e3.json" --camera 0,50,0,0,60,0 || bad "all-miss eval exited $?"
python3 - "$work/e3.json" <<'PY' || bad "all-miss eval report"
import json, sys
r = json.load(open(sys.argv[1]))
for e in ("shadow", "ao", "reflection", "combined"):
    assert r["images"][e]["flip_mean"] == 0.0, r["images"][e]  # both images are all background
    assert r["images"][e]["flip_mean_lsnif_pixels"] is None, r["images"][e]  # no LSNIF pixel
assert r["lsnif_pixels"] == 0, r["lsnif_pixels"]
PY

# Copy OUTDIR alone: its inputs are gone. One error line naming the missing source, exit 1,
# no image or .tmp left behind.
cp -r "$work/moved/out" "$work/lonely"
expect_error() { # NAME PATTERN command...
  local name=$1 pattern=$2
  shift 2
  "$@" >/dev/null 2>"$work/err"
  local rc=$?
  [[ $rc == 1 ]] || bad "$name: exit $rc, $(cat "$work/err")"
  [[ $(wc -l <"$work/err") == 1 ]] || bad "$name: not one line: $(cat "$work/err")"
  grep -q "^error: .*$pattern" "$work/err" || bad "$name: message: $(cat "$work/err")"
}
expect_error "render, inputs gone" "src/scene.glb" "$render" "$work/lonely" "$work/gone.ppm" 32 24
[[ ! -e $work/gone.ppm && ! -e $work/gone.ppm.tmp ]] || bad "render with inputs gone left a file"
expect_error "eval, inputs gone" "src/scene.glb" "$lsnif" eval "$work/lonely" --images "$work/gone_img"
[[ ! -e $work/gone_img ]] || bad "eval with inputs gone wrote images"
expect_error "bench, inputs gone" "src/scene.glb" "$lsnif" bench memory "$work/lonely"

# An older manifest (absolute or cwd-relative paths, format /1): asked to re-convert.
sed -i 's#lsnif-manifest/4#lsnif-manifest/1#' "$work/lonely/manifest.json"
expect_error "render, old format" "re-run lsnif convert" "$render" "$work/lonely" "$work/old.ppm" 32 24
expect_error "eval, old format" "re-run lsnif convert" "$lsnif" eval "$work/lonely" --images "$work/old_img"
# A torn manifest: named, exit 1.
head -c 200 "$work/moved/out/manifest.json" >"$work/lonely/manifest.json"
expect_error "render, torn manifest" "manifest.json" "$render" "$work/lonely" "$work/torn.ppm" 32 24
expect_error "eval, torn manifest" "manifest.json" "$lsnif" eval "$work/lonely" --images "$work/torn_img"
[[ ! -e $work/old.ppm && ! -e $work/torn.ppm ]] || bad "a failed render left an image"
# Usage errors exit 2.
"$render" "$work/moved/out" 2>/dev/null; rc=$?
[[ $rc == 2 ]] || bad "render without OUT.ppm: exit $rc"
"$render" "$work/moved/out" "$work/x.ppm" 32 24 --camera 1,2,3 2>/dev/null; rc=$?
[[ $rc == 2 ]] || bad "render with a short --camera: exit $rc"
exit $fail
