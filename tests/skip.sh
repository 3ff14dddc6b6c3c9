# Sourced by the shell tests: `skip_or_fail NEED MESSAGE` ends a test that cannot run here.
# NEED names what it lacks: a service (nginx, slurm) or an instruction-set level (avx2,
# avx512, avx512bf16, amx). Normally it prints "SKIP: MESSAGE" and exits 77, which CTest
# reports as skipped. When NEED is listed in LSNIF_TEST_EXPECT (comma-separated: what this
# runner must have; scripts/test expects the services it installs), the test fails instead:
# on a runner that should have it, a broken set-up must not turn green.
skip_or_fail() {
  local need=$1
  shift
  if [[ ,${LSNIF_TEST_EXPECT:-}, == *,"$need",* ]]; then
    echo "FAIL: $* (LSNIF_TEST_EXPECT=${LSNIF_TEST_EXPECT} says this runner has $need)"
    exit 1
  fi
  echo "SKIP: $*"
  exit 77
}
