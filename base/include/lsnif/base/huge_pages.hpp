// The toolchain's one allocator for large, randomly accessed buffers (header-only): blocks of
// at least kHugePageBytes are aligned to 2 MiB and offered to Linux as transparent huge pages
// (madvise MADV_HUGEPAGE), smaller ones come from operator new.
//
// Why: the trainer's prepared rays (hundreds of MB, refilled every round of streamed rays
// and read at random indices every step) cost one page fault per 4 KiB when first touched
// and one TLB miss per random access. Debian's kernels default to THP "madvise", so
// without the advice they never get huge pages. Measured in docs/investigations/conversion-time.md
// "Huge pages for the prepared rays". Where the kernel refuses (THP "never", other systems) the advice is
// ignored and the memory behaves as before: results never depend on it.
//
// Contract: allocate/deallocate pair as for std::allocator; not for memory shared with C.
#pragma once

#include <cstddef>
#include <cstdlib>
#include <new>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace lsnif::base {

inline constexpr std::size_t kHugePageBytes = std::size_t(2) << 20;

// n bytes (n > 0); huge-page backed when n >= kHugePageBytes. Throws std::bad_alloc.
inline void* allocate_large(std::size_t n) {
    if (n < kHugePageBytes) return ::operator new(n);
    const std::size_t rounded = (n + kHugePageBytes - 1) / kHugePageBytes * kHugePageBytes;
    void* p = std::aligned_alloc(kHugePageBytes, rounded);
    if (!p) throw std::bad_alloc();
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    ::madvise(p, rounded, MADV_HUGEPAGE);  // advice only: failure leaves normal pages
#endif
    return p;
}

// Frees what allocate_large(n) returned, with the same n.
inline void free_large(void* p, std::size_t n) noexcept {
    if (n < kHugePageBytes)
        ::operator delete(p);
    else
        std::free(p);
}

}  // namespace lsnif::base
