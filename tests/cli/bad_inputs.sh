#!/usr/bin/env bash
# Bad input never crashes `lsnif convert`: every file under assimp-testmodels'
# glTF2/ and invalid/ folders, CGAL's degenerate, self-intersecting, holed and badly
# oriented meshes, the import fuzz corpus (node cycles, Draco, missing buffers, NaN,
# absurd counts, ... with the format byte stripped) and cases generated here (huge and tiny
# coordinates, zero-area triangles, empty meshes, absurd accessor counts) are converted
# one per process with the smoke preset, trained for 30 steps (what a file does to the
# pipeline shows in the first steps; the rest would only cost time). Each run must
#   * end by itself within the timeout with exit status 0 or 1 (never a signal or abort),
#   * on failure print an "error: FILE: ..." line naming the file and leave no OUTDIR,
#   * on success leave only manifest.json and .lsnif files (no temporaries), and print any
#     skipped content as "warning:" lines.
# Which files are rejected and which convert is compared with tests/cli/bad_inputs.expected:
# an importer change that starts rejecting a file (or accepting a broken one) fails here.
# Then a multi-input run with good and bad inputs must convert the good ones, report every
# bad one, and exit 1.
# usage: bad_inputs.sh LSNIF_BINARY CGAL_ARCHIVE WORK_DIR [TIMEOUT_SECONDS]
set -uo pipefail
lsnif=$1 archive=$2 work=$3 limit=${4:-300}
src=$(cd "$(dirname "$0")/.." && pwd)
fail=0 runs=0 errors=0 oks=0 gltfs=()
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work/in" "$work/cgal"

# CGAL's awkward meshes: holes, open surfaces, self-intersections, shuffled orientation,
# degenerate (sliding, folded) triangles, several components, polygons.
cgal=(degtri_sliding fold tetra_intersected_by_triangle cube-shuffled cube4-shuffled tet-shuffled
      hole holes triangular_hole corner_with_hole corner_tris_with_hole hedra_open open_cube cube-ouvert
      quads_to_stitch negative in triangle quad mesh_with_border elephant-with-holes blobby_3cc
      double-torus-3-holes mech-holes-shark polygon_mesh)
members=()
for n in "${cgal[@]}"; do members+=("data/meshes/$n.off"); done
tar xzf "$archive" -C "$work/cgal" "${members[@]}" || bad "cannot extract CGAL's meshes from $archive"

# The fuzz corpus, back to plain files (first byte = format: gltf glb obj ply off stl).
exts=(gltf glb obj ply off stl)
for f in "$src"/fuzz/corpus/import/*; do
  k=$(od -An -tu1 -N1 "$f" | tr -d ' ')
  tail -c +2 "$f" >"$work/in/corpus_$(basename "$f").${exts[k % 6]}"
done

# Generated here.
printf 'OFF\n3 1 0\n3e38 0 0\n-3e38 3e38 0\n0 -3e38 3e38\n3 0 1 2\n' >"$work/in/huge_coordinates.off"
printf 'OFF\n3 1 0\n1e-40 0 0\n0 1e-40 0\n0 0 1e-40\n3 0 1 2\n' >"$work/in/denormal_coordinates.off"
printf 'OFF\n4 2 0\n0 0 0\n1 1 1\n2 2 2\n3 3 3\n3 0 1 2\n3 1 2 3\n' >"$work/in/zero_area.off"
printf 'OFF\n0 0 0\n' >"$work/in/empty.off"
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\ninf 1 0\n3 0 1 2\n' >"$work/in/inf_vertex.off"
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 -1\n' >"$work/in/negative_index.off"
printf 'OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n300 0 1 2\n' >"$work/in/absurd_polygon.off"
printf '' >"$work/in/zero_bytes.glb"
printf 'glTF\002\000\000\000\377\377\377\377' >"$work/in/absurd_length.glb"
cat >"$work/in/absurd_count.gltf" <<'GLTF'
{"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}],
 "meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],
 "buffers":[{"byteLength":36,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}],
 "bufferViews":[{"buffer":0,"byteLength":36}],
 "accessors":[{"bufferView":0,"componentType":5126,"count":4000000000,"type":"VEC3"}]}
GLTF
cat >"$work/in/huge_scale_node.gltf" <<'GLTF'
{"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0,"scale":[1e38,1e38,1e38]}],
 "meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],
 "buffers":[{"byteLength":36,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}],
 "bufferViews":[{"buffer":0,"byteLength":36}],
 "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}]}
GLTF

# A file's name in the outcome list: where it comes from, without this machine's paths.
label() {
  local f=$1
  f=${f#/usr/share/assimp/models/}
  f=${f#$work/cgal/data/meshes/}
  f=${f#$work/in/}
  echo "$f"
}
check_one() {  # FILE
  local file=$1 out=$work/out_$runs
  runs=$((runs + 1))
  timeout -k 10 "$limit" "$lsnif" convert "$file" -o "$out" --preset smoke --steps 30 --threads 2 --seed 3 \
    >"$work/stdout" 2>"$work/stderr"
  local rc=$?
  if ((rc == 124 || rc == 137)); then bad "$file: did not finish within ${limit}s"; return; fi
  if ((rc != 0 && rc != 1)); then bad "$file: exit status $rc (signal or abort)"; head -5 "$work/stderr"; return; fi
  if ((rc == 1)); then
    errors=$((errors + 1))
    echo "rejected $(label "$file")" >>"$work/outcomes"
    grep -q "^error: .*$(basename "$file")" "$work/stderr" || { bad "$file: no error line naming the file"; head -3 "$work/stderr"; }
    [[ -e $out ]] && bad "$file: failed but left $out behind"
  else
    oks=$((oks + 1))
    echo "converted $(label "$file")" >>"$work/outcomes"
    [[ -f $out/manifest.json ]] || bad "$file: succeeded without a manifest"
    local stray
    stray=$(find "$out" -mindepth 1 ! -name manifest.json ! -name '*.lsnif' ! -name scene.gltf ! -name scene.bin)
    [[ -z $stray ]] || bad "$file: stray files: $stray"
    gltfs+=("$out/scene.gltf")  # imported again below, all in one process
  fi
  # Captured, not piped into `grep -q`: under pipefail a producer killed by SIGPIPE when grep
  # stops early would turn a found line into a pass.
  local unexpected
  unexpected=$(grep -v -e '^error: ' -e '^warning: ' -e '^\[' -e '^ ' "$work/stderr" || true)
  [[ -z $unexpected ]] || { bad "$file: unexpected stderr text"; head -3 <<<"$unexpected"; }
  if [[ -f $out/scene.gltf ]]; then rm -f "$out"/*.lsnif; else rm -rf "$out"; fi  # keep what is re-imported
}

while IFS= read -r -d '' f; do check_one "$f"; done < <(
  find /usr/share/assimp/models/glTF2 /usr/share/assimp/models/invalid "$work/cgal" "$work/in" -type f -print0 | sort -z)

expected=$src/cli/bad_inputs.expected
sort "$work/outcomes" >"$work/outcomes.sorted"
diff "$expected" "$work/outcomes.sorted" >"$work/outcomes.diff" ||
  bad "outcomes differ from $(basename "$expected") (< expected, > this run): $(head -20 "$work/outcomes.diff")"

# Several inputs, some bad: the good ones are converted, each bad one is reported, exit 1.
good1=/usr/share/assimp/models/glTF2/BoxTextured-glTF/BoxTextured.gltf
good2=$work/cgal/data/meshes/hole.off
timeout -k 10 "$limit" "$lsnif" convert "$good1" "$work/in/empty.off" "$good2" "$work/in/absurd_count.gltf" \
  -o "$work/multi" --preset smoke --threads 2 >"$work/stdout" 2>"$work/stderr"
rc=$?
((rc == 1)) || bad "multi-input run: exit $rc, expected 1"
grep -q "^error: .*empty.off" "$work/stderr" || bad "multi-input run: empty.off not reported"
grep -q "^error: .*absurd_count.gltf" "$work/stderr" || bad "multi-input run: absurd_count.gltf not reported"
[[ -f $work/multi/manifest.json ]] || bad "multi-input run: no manifest for the good inputs"
grep -q '"status": "ok"' "$work/multi/manifest.json" 2>/dev/null || bad "multi-input run: good inputs not converted"

# Every scene.gltf written (the input kept whole, buffers and images re-pointed from OUTDIR)
# imports again: one dry run over all of them, which names any that does not.
"$lsnif" convert "${gltfs[@]}" -o "$work/again" --dry-run --preset smoke >/dev/null 2>"$work/stderr_again" \
  || bad "scene.gltf files that do not import: $(grep '^error' "$work/stderr_again" | head -5)"
((${#gltfs[@]} == oks)) || bad "${#gltfs[@]} scene.gltf files for $oks conversions"
echo "bad_inputs: $runs files, $oks converted, $errors rejected with an error line; multi-input run checked"
((runs >= 120)) || bad "only $runs files ran"
exit $fail
