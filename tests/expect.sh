#!/usr/bin/env bash
# expect.sh STATUS REGEX COMMAND ARGS...: passes when COMMAND exits with STATUS and its
# output (stdout and stderr together) matches the extended REGEX. For CTest, where
# PASS_REGULAR_EXPRESSION alone ignores the exit status and WILL_FAIL accepts any failure,
# a crash included.
set -u
want=$1 regex=$2
shift 2
out=$("$@" 2>&1)
got=$?
[[ $got == "$want" ]] || { echo "FAIL: exit status $got, want $want: $*"; echo "$out"; exit 1; }
grep -Eq -- "$regex" <<<"$out" || { echo "FAIL: output does not match /$regex/: $*"; echo "$out"; exit 1; }
echo "$out"
