// Heap bytes held by standard containers: what an allocator hands out for them, counted from
// their capacities (libstdc++: a vector allocates capacity() elements, a string outside its
// small-string buffer capacity() + 1 bytes). Internal to format/: the resident bytes of a
// handle (lsnif_info::decoded_bytes) are the sum of these over everything it owns, checked
// against a counting allocator by tests/format/test_resident.cpp.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace lsnif::format::detail {

template <class T>
std::uint64_t heap_bytes(const std::vector<T>& v) {
    return std::uint64_t(v.capacity()) * sizeof(T);
}

template <class T>
std::uint64_t heap_bytes(const std::vector<std::vector<T>>& vv) {
    std::uint64_t n = std::uint64_t(vv.capacity()) * sizeof(std::vector<T>);
    for (const auto& v : vv) n += heap_bytes(v);
    return n;
}

inline std::uint64_t heap_bytes(const std::string& s) {
    // The small-string buffer lives inside the object: nothing on the heap.
    constexpr std::size_t kInline = 15;
    return s.capacity() > kInline ? std::uint64_t(s.capacity()) + 1 : 0;
}

}  // namespace lsnif::format::detail
