// Whether this build compiles the reader's x86 vector kernels (LSNIF_HAVE_X86 = 1: GCC or
// Clang on x86-64) or only its portable code (0: other CPUs and compilers, and any build
// with LSNIF_PORTABLE defined — the CMake option of the same name, with which the format
// tests check the portable code on an x86 machine). The kernels are chosen at run time by
// cpu_features(); with LSNIF_HAVE_X86 = 0 they do not exist and cpu_features() reports
// no vector extension. Internal to format/src.
#pragma once

#if defined(__x86_64__) && defined(__GNUC__) && !defined(LSNIF_PORTABLE)
#define LSNIF_HAVE_X86 1
#include <cpuid.h>
#include <immintrin.h>
#else
#define LSNIF_HAVE_X86 0
#endif
