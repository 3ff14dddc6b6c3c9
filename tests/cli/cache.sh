#!/usr/bin/env bash
# `lsnif convert --cache` as processes: two conversions sharing one cache at the same time
# both succeed with identical assets; a third run finds everything; two `lsnif batch` runs
# at once agree byte for byte; a cache path that cannot be a directory is an error naming it.
# usage: cache.sh LSNIF_BINARY MESH_DIR WORK_DIR
set -uo pipefail
lsnif=$1 meshes=$2 work=$3
fail=0
bad() { echo "FAIL: $*"; fail=1; }
rm -rf "$work" && mkdir -p "$work"
inputs=("$meshes/ChineseDragon-10kv.off" "$meshes/armadillo.off")

for k in 1 2; do
  "$lsnif" convert "${inputs[@]}" -o "$work/out$k" --preset smoke --threads 1 --cache "$work/cache" --json \
    >"$work/report$k.json" 2>"$work/err$k" &
done
wait %1 || bad "first concurrent run exited $?: $(cat "$work/err1")"
wait %2 || bad "second concurrent run exited $?: $(cat "$work/err2")"
for f in "$work"/out1/*.lsnif; do
  cmp -s "$f" "$work/out2/$(basename "$f")" || bad "$(basename "$f") differs between the concurrent runs"
done
[[ $(ls "$work"/out1/*.lsnif | wc -l) == 2 ]] || bad "expected two assets"
grep -q "corrupt" "$work/err1" "$work/err2" && bad "a concurrent run saw a corrupt entry"

"$lsnif" convert "${inputs[@]}" -o "$work/out3" --preset smoke --threads 1 --cache "$work/cache" --json \
  >"$work/report3.json" 2>"$work/err3" || bad "third run exited $?"
python3 - "$work/report3.json" <<'PY' || bad "third run: not all cache hits"
import json, sys
r = json.load(open(sys.argv[1]))
assert r["cache"]["hits"] == 2 and r["cache"]["stored"] == 0, r["cache"]
PY
for f in "$work"/out1/*.lsnif; do
  cmp -s "$f" "$work/out3/$(basename "$f")" || bad "$(basename "$f") differs in the warm run"
done

# Two `lsnif batch` processes sharing a fresh cache at the same time: both succeed, with the
# same manifest and assets.
for k in 1 2; do
  "$lsnif" batch "${inputs[@]}" -o "$work/batch$k" --preset smoke --threads 1 --cache "$work/batch_cache" \
    >"$work/batch$k.out" 2>"$work/batch_err$k" &
done
wait %1 || bad "first concurrent batch exited $?: $(cat "$work/batch_err1")"
wait %2 || bad "second concurrent batch exited $?: $(cat "$work/batch_err2")"
cmp -s "$work/batch1/manifest.json" "$work/batch2/manifest.json" || bad "the concurrent batches' manifests differ"
for f in "$work"/batch1/*.lsnif; do
  cmp -s "$f" "$work/batch2/$(basename "$f")" || bad "$(basename "$f") differs between the concurrent batches"
done
[[ $(ls "$work"/batch1/*.lsnif | wc -l) == 2 ]] || bad "expected two assets from each batch"

echo "not a directory" >"$work/blocked"
"$lsnif" convert "${inputs[0]}" -o "$work/out4" --preset smoke --cache "$work/blocked/c" 2>"$work/err4"; rc=$?
[[ $rc == 1 ]] || bad "unusable cache directory: exit $rc"
grep -q "^error: $work/blocked/c: cannot create the cache directory" "$work/err4" || bad "cache error: $(cat "$work/err4")"
exit $fail
