#!/usr/bin/env bash
# README.md's "Every command and option" is the command line's own (`lsnif --help-markdown`):
# fails, with the difference, when an option was added, renamed or described otherwise.
# usage: readme_options.sh LSNIF_BINARY PROJECT_DIR WORK_DIR
set -uo pipefail
lsnif=$1 project=$2 work=$3
rm -rf "$work" && mkdir -p "$work"
"$lsnif" --help-markdown >"$work/cli.md" || { echo "FAIL: lsnif --help-markdown: exit $?"; exit 1; }
sed -n '/<!-- lsnif --help-markdown: begin -->/,/<!-- lsnif --help-markdown: end -->/p' "$project/README.md" \
  | sed '1d;$d' >"$work/readme.md"
[[ -s $work/readme.md ]] || { echo "FAIL: README.md has no generated option tables"; exit 1; }
grep -q '^### `lsnif batch`' "$work/cli.md" && grep -q -- '--from-plan' "$work/cli.md" \
  || { echo "FAIL: the generated tables miss lsnif batch's options"; exit 1; }
# Trailing blank lines aside (the README section ends at its marker).
# (Read before writing: open(p, 'w') empties the file.)
for f in readme cli; do
  python3 -c "import sys; p = sys.argv[1]; t = open(p).read(); open(p, 'w').write(t.rstrip('\n') + '\n')" "$work/$f.md"
done
if ! diff -u "$work/readme.md" "$work/cli.md" >"$work/diff.txt"; then
  echo "FAIL: README.md's option tables differ from the command line (run scripts/readme-options):"
  head -40 "$work/diff.txt"
  exit 1
fi
echo "PASS: README option tables == lsnif --help-markdown"
