#!/usr/bin/env bash
# lsnif(1) and the bash completion the build generates next to lsnif (and the tools package
# installs): the page renders without a groff warning and names every subcommand and option
# of the command line; the completion offers every option of every subcommand, the choices
# of a choice-valued option, and file names where a value is a path.
# usage: man_completion.sh LSNIF_BINARY WORK_DIR
set -uo pipefail
lsnif=$1 work=$2
rm -rf "$work" && mkdir -p "$work"
fail() { echo "FAIL: $*"; exit 1; }
dir=$(dirname "$lsnif")
[[ -f $dir/lsnif.1.gz && -f $dir/lsnif.bash ]] || fail "the build made no $dir/lsnif.1.gz or $dir/lsnif.bash"
"$lsnif" --help-man >"$work/lsnif.1" || fail "lsnif --help-man: exit $?"
"$lsnif" --completion-bash >"$work/lsnif.bash" || fail "lsnif --completion-bash: exit $?"
cmp -s <(zcat "$dir/lsnif.1.gz") "$work/lsnif.1" || fail "$dir/lsnif.1.gz is not what lsnif --help-man prints"
cmp -s "$dir/lsnif.bash" "$work/lsnif.bash" || fail "$dir/lsnif.bash is not what lsnif --completion-bash prints"

# The reference every check below compares with: subcommand paths and their options.
"$lsnif" --help-markdown >"$work/cli.md" || fail "lsnif --help-markdown: exit $?"
python3 - "$work/cli.md" >"$work/options.txt" <<'PY' || fail "cannot read the option tables"
import re, sys
path = None
for line in open(sys.argv[1]):
    m = re.match(r"^### `lsnif (.*)`$", line)
    if m:
        path = m.group(1)
        print(path)
        continue
    m = re.match(r"^\| `([^`]*)` \|", line)
    if m and path and m.group(1) != "option":
        for name in m.group(1).split(","):
            if name.startswith("-"):
                print(path + "\t" + name)
PY
(($(wc -l <"$work/options.txt") > 80)) || fail "only $(wc -l <"$work/options.txt") subcommands and options found"

# The page: no groff warning, every subcommand and option in the rendered text.
command -v groff >/dev/null || fail "groff is missing (scripts/setup installs groff-base)"
groff -man -Tutf8 -ww -z "$work/lsnif.1" 2>"$work/groff.txt" || fail "groff failed on lsnif.1"
[[ ! -s $work/groff.txt ]] || fail "groff warns about lsnif.1: $(head -5 "$work/groff.txt")"
MANWIDTH=200 groff -man -Tascii -P-cbou "$work/lsnif.1" >"$work/page.txt" 2>/dev/null
missing=0
while IFS=$'\t' read -r sub name; do
    if [[ -z ${name:-} ]]; then
        grep -qF "lsnif $sub" "$work/page.txt" || { echo "man page lacks subcommand 'lsnif $sub'"; missing=1; }
    else
        grep -qF -- "$name" "$work/page.txt" || { echo "man page lacks $sub $name"; missing=1; }
    fi
done <"$work/options.txt"
((missing == 0)) || fail "the man page does not name everything lsnif accepts"
for section in SYNOPSIS COMMANDS "EXIT STATUS" ENVIRONMENT FILES; do
    grep -q "^$section" "$work/page.txt" || fail "the man page has no $section section"
done

# The completion, run as bash runs it: COMP_WORDS/COMP_CWORD in, COMPREPLY out.
bash -n "$work/lsnif.bash" || fail "lsnif.bash is not valid bash"
complete_words() {
    (cd "$work" && bash -c 'source ./lsnif.bash; COMP_WORDS=("$@"); COMP_CWORD=$(($# - 1)); _lsnif; printf "%s\n" "${COMPREPLY[@]}"' _ "$@")
}
[[ $(complete_words lsnif con) == convert ]] || fail "'lsnif con' does not complete to convert"
[[ $(complete_words lsnif bench '' | sort | tr '\n' ' ') == "convert infer memory rays train " ]] ||
    fail "'lsnif bench ' offers: $(complete_words lsnif bench '' | tr '\n' ' ')"
[[ $(complete_words lsnif convert --accept '' | tr '\n' ' ') == "rays images either " ]] ||
    fail "'lsnif convert --accept ' offers: $(complete_words lsnif convert --accept '' | tr '\n' ' ')"
[[ $(complete_words lsnif convert --preset fast --accept im) == images ]] ||
    fail "an earlier option's value confuses the completion of --accept"
touch "$work/scene.glb"
[[ $(complete_words lsnif convert -o '' scene.g) == scene.glb ]] || fail "inputs do not complete to file names"
[[ $(complete_words lsnif convert --output sc) == scene.glb ]] || fail "--output DIR does not complete to file names"
[[ -z $(complete_words lsnif convert --steps '') ]] || fail "--steps N offers words"
missing=0
cut -f1 "$work/options.txt" | sort -u >"$work/subs.txt"
while read -r sub; do
    read -ra words <<<"lsnif $sub"
    complete_words "${words[@]}" - | sort >"$work/offered.txt"
    while IFS=$'\t' read -r s name; do
        [[ $s == "$sub" && -n ${name:-} ]] || continue
        grep -qxF -- "$name" "$work/offered.txt" || { echo "'lsnif $sub -' does not offer $name"; missing=1; }
    done <"$work/options.txt"
done <"$work/subs.txt"
((missing == 0)) || fail "the completion does not offer every option"
echo "PASS: lsnif(1) and the bash completion describe every subcommand and option"
