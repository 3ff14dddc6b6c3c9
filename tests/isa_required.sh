#!/usr/bin/env bash
# isa_required.sh LEVEL [--cap] COMMAND ARGS...: runs COMMAND when this CPU offers LEVEL
# (avx2, avx512, avx512bf16, avx512vnni, amx; generic always), else prints what it lacks and exits 77,
# which CTest reports as skipped (SKIP_RETURN_CODE), so a green run says what did not run;
# it fails instead when LSNIF_TEST_EXPECT lists LEVEL (tests/skip.sh).
# With --cap, COMMAND runs with LSNIF_ISA=LEVEL: lsnif's kernels limited to that level.
# isa_required.sh --missing LEVEL prints what the CPU lacks for LEVEL (nothing: it has it).
set -u
. "$(dirname "$0")/skip.sh"
flags=" $(grep -m1 '^flags' /proc/cpuinfo | cut -d: -f2) "
missing() {
  local need=()
  case $1 in
    generic) ;;
    avx2) need=(avx2 fma) ;;
    avx512) need=(avx2 fma avx512f avx512bw avx512dq avx512vl) ;;
    avx512bf16) need=(avx2 fma avx512f avx512bw avx512dq avx512vl avx512_bf16) ;;
    avx512vnni) need=(avx2 fma avx512f avx512bw avx512dq avx512vl avx512_vnni) ;;
    amx) need=(avx2 fma avx512f avx512bw avx512dq avx512vl avx512_bf16 amx_bf16 amx_tile) ;;
    *) echo "isa_required.sh: unknown level $1" >&2; exit 2 ;;
  esac
  local out=()
  for f in "${need[@]}"; do [[ $flags == *" $f "* ]] || out+=("$f"); done
  echo "${out[*]}"
}
if [[ ${1:-} == --missing ]]; then
  missing "$2"
  exit 0
fi
level=$1
shift
cap=0
[[ ${1:-} == --cap ]] && { cap=1; shift; }
lacks=$(missing "$level")
[[ -z $lacks ]] || skip_or_fail "$level" "this CPU lacks $lacks, needed for $level"
if ((cap)); then
  LSNIF_ISA=$level exec "$@"
fi
exec "$@"
