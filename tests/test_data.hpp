// Reading the repository's test data (tests/data, LSNIF_TEST_DATA_DIR) from doctest cases:
// one helper of each kind for every test executable that reads golden files.
#pragma once

#include <doctest/doctest.h>

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <vector>

namespace lsnif::test {

// The whole file; fails the calling test case (REQUIRE) when it cannot be opened.
inline std::vector<std::uint8_t> load(const std::filesystem::path& p) {
    std::ifstream f(p, std::ios::binary);
    REQUIRE_MESSAGE(f.good(), "cannot open " << p);
    return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

#ifdef LSNIF_TEST_DATA_DIR
// The repository's tests/data directory, as the build passes it to the test.
inline std::filesystem::path data_dir() {
    return std::filesystem::path(LSNIF_TEST_DATA_DIR);
}
#endif

}  // namespace lsnif::test
