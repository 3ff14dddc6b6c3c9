// Test helpers shared by every test executable: reading files and the repository's test data
// (tests/data, LSNIF_TEST_DATA_DIR), and fresh work directories:
// one helper of each kind for every test executable that reads golden files.
#pragma once

#include <doctest/doctest.h>

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

namespace lsnif::test {

// The whole file; fails the calling test case (REQUIRE) when it cannot be opened.
inline std::vector<std::uint8_t> load(const std::filesystem::path& p) {
    std::ifstream f(p, std::ios::binary);
    REQUIRE_MESSAGE(f.good(), "cannot open " << p);
    return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

// ROOT/NAME with everything under it removed; created again as an empty directory when
// `create`, else left absent (for a test that expects a tool to create it).
inline std::filesystem::path fresh_dir(const std::filesystem::path& root, const std::string& name,
                                       bool create = true) {
    const std::filesystem::path dir = root / name;
    std::filesystem::remove_all(dir);
    if (create) std::filesystem::create_directories(dir);
    return dir;
}

// Whether LSNIF_TEST_EXPECT (comma-separated, tests/skip.sh) lists `need`: what this runner
// must have, so that a case that cannot run for want of it fails instead of being passed by.
inline bool runner_expects(const std::string& need) {
    const char* e = std::getenv("LSNIF_TEST_EXPECT");
    return e && ("," + std::string(e) + ",").find("," + need + ",") != std::string::npos;
}

#ifdef LSNIF_TEST_DATA_DIR
// The repository's tests/data directory, as the build passes it to the test.
inline std::filesystem::path data_dir() {
    return std::filesystem::path(LSNIF_TEST_DATA_DIR);
}
#endif

}  // namespace lsnif::test
