#!/usr/bin/env bash
# Regenerates the golden files and requires them byte-identical to the committed ones.
# usage: compare.sh GEN_GOLDEN COMMITTED_DATA_DIR WORK_DIR
set -uo pipefail
gen=$1 committed=$2 work=$3
rm -rf "$work" && "$gen" "$work" || exit 1
fail=0
for kind in valid invalid; do
  for f in "$work/$kind"/*.lsnif; do
    cmp -s "$f" "$committed/$kind/$(basename "$f")" || { echo "differs or missing: $kind/$(basename "$f")"; fail=1; }
  done
  for f in "$committed/$kind"/*.lsnif; do
    [[ -f "$work/$kind/$(basename "$f")" ]] || { echo "committed but not generated: $kind/$(basename "$f")"; fail=1; }
  done
done
exit $fail
