#!/usr/bin/env bash
# End-to-end checks of `lsnif inspect` and `lsnif validate` as processes: exit codes,
# one `error:` line per problem, and no signal on damaged input.
# usage: cli_file_tools.sh LSNIF_BINARY DATA_DIR WORK_DIR
set -uo pipefail
lsnif=$1 data=$2 work=$3
fail=0
bad() { echo "FAIL: $*"; fail=1; }
mkdir -p "$work"

# Valid files: exit 0, "ok" per file, JSON says valid.
out=$("$lsnif" validate "$data"/valid/*.lsnif) || bad "validate of valid files exited $?"
[[ $(grep -c ': ok$' <<<"$out") == $(ls "$data"/valid/*.lsnif | wc -l) ]] || bad "not one ok line per valid file: $out"
[[ $("$lsnif" validate --json "$data/valid/tiny.lsnif") == *'"valid": true'* ]] || bad "validate --json"

# Invalid files: exit exactly 1 (not a signal), each prints an error line naming the file.
for f in "$data"/invalid/*.lsnif; do
  err=$("$lsnif" validate "$f" 2>&1 >/dev/null); rc=$?
  [[ $rc == 1 ]] || bad "$f: exit $rc"
  grep -q "^$f: error: " <<<"$err" || bad "$f: no error line: $err"
done
# Mixed list: still exit 1, and the good file is reported ok.
out=$("$lsnif" validate "$data/valid/tiny.lsnif" "$data/invalid/payload_checksum.lsnif" 2>&1); rc=$?
[[ $rc == 1 ]] || bad "mixed validate exit $rc"
grep -q 'tiny.lsnif: ok' <<<"$out" || bad "mixed validate lost the ok line"
"$lsnif" validate /nonexistent.lsnif 2>/dev/null; [[ $? == 1 ]] || bad "missing file exit code"

# LSNIF_ISA: a cap that names no level is a usage error (exit 2, one error line); a level is
# accepted, whatever this CPU has (a cap never adds an instruction set).
LSNIF_ISA=avx9 "$lsnif" validate "$data/valid/tiny.lsnif" >/dev/null 2>"$work/isa.err"; rc=$?
[[ $rc == 2 ]] && grep -q '^error: LSNIF_ISA=avx9: not one of generic, avx2, avx512, avx512bf16, amx$' "$work/isa.err" \
  || bad "unknown LSNIF_ISA: exit $rc $(cat "$work/isa.err")"
for cap in generic avx2 avx512 avx512bf16 amx; do
  LSNIF_ISA=$cap "$lsnif" validate "$data/valid/tiny.lsnif" >/dev/null || bad "LSNIF_ISA=$cap validate exited $?"
done

# inspect: text and JSON on a valid file; clean failure on a damaged one.
out=$("$lsnif" inspect "$data/valid/v1_default.lsnif") || bad "inspect exit $?"
for want in "format version 1.0" "GRID" "MLPW" "108 -> 128 -> 128 -> 5" "lsnif-metadata/1"; do
  grep -qF -- "$want" <<<"$out" || bad "inspect output lacks '$want'"
done
grep -q '"input_width": 108' <<<"$("$lsnif" inspect --json "$data/valid/v1_default.lsnif")" || bad "inspect --json"
"$lsnif" inspect "$data/invalid/table_checksum.lsnif" >/dev/null 2>&1; [[ $? == 1 ]] || bad "inspect of damaged file"

# Truncations and header/table bit flips of a valid file, as processes (exit code 1, never
# a signal). Every truncation and every flip is also checked in-process through the same
# validate code (tests/cli/test_file_tools.cpp); here a sample checks that the
# process turns each kind of damage into exit 1, and keeps the sanitizer run short (a
# sanitized process start costs a third of a second of CPU): every 19th offset in header and
# table, every 97th beyond; one bit of every 19th header/table byte, cycling through the bit
# positions.
src="$data/valid/tiny.lsnif"
size=$(stat -c %s "$src")
for ((n = 0; n < size; n += (n < 384 ? 19 : 97))); do
  head -c "$n" "$src" >"$work/t.lsnif"
  "$lsnif" validate "$work/t.lsnif" >/dev/null 2>&1; rc=$?
  [[ $rc == 1 ]] || { bad "truncation to $n bytes: exit $rc"; break; }
done
for ((byte = 0; byte < 384; byte += 19)); do
  for bit in $(((byte / 19) % 8)); do
    cp "$src" "$work/f.lsnif"
    orig=$(od -An -tu1 -j "$byte" -N1 "$src" | tr -d ' ')
    printf "$(printf '\\%03o' $((orig ^ (1 << bit))))" | dd of="$work/f.lsnif" bs=1 seek="$byte" conv=notrunc status=none
    "$lsnif" validate "$work/f.lsnif" >/dev/null 2>&1; rc=$?
    [[ $rc == 1 ]] || { bad "flip byte $byte bit $bit: exit $rc"; break 2; }
  done
done
exit $fail
