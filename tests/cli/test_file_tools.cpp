// `lsnif validate` / `lsnif inspect` logic.
#include <doctest/doctest.h>

#include "../test_data.hpp"

#include <lsnif/cli/file_tools.hpp>

#include <filesystem>
#include <fstream>

using namespace lsnif::cli;
using nlohmann::json;
namespace fs = std::filesystem;

using lsnif::test::load;

namespace {
std::string load_text(const fs::path& p) {
    auto b = load(p);
    return {b.begin(), b.end()};
}
fs::path data_dir() {
    return fs::path(LSNIF_TEST_DATA_DIR);
}
}  // namespace

TEST_CASE("golden valid files validate with no problem") {
    int n = 0;
    for (const auto& e : fs::directory_iterator(data_dir() / "valid")) {
        const auto r = validate_file(e.path().string());
        CHECK_MESSAGE(r.valid(), r.to_text());
        ++n;
    }
    CHECK(n >= 4);
}

TEST_CASE("each golden invalid file fails with exactly its expected error") {
    int n = 0;
    for (const auto& e : fs::directory_iterator(data_dir() / "invalid")) {
        if (e.path().extension() != ".lsnif") continue;
        ++n;
        const fs::path expected = fs::path(e.path()).replace_extension(".expected");
        REQUIRE_MESSAGE(fs::exists(expected), "missing " << expected);
        const auto r = validate_bytes(load(e.path()), e.path().filename().string());
        REQUIRE_MESSAGE(!r.valid(), e.path());
        std::string got;
        for (const auto& p : r.problems)
            got += p.status + ": " + p.message +
                   (p.offset != UINT64_MAX ? " @" + std::to_string(p.offset) : "") + "\n";
        CHECK_MESSAGE(got == load_text(expected), e.path().filename().string() << "\n--- got:\n" << got);
    }
    CHECK(n >= 30);
}

TEST_CASE("validate rejects every truncation, reports one line per problem") {
    const auto bytes = load(data_dir() / "valid" / "dense_uncompressed.lsnif");
    for (std::size_t n = 0; n < bytes.size(); ++n) {
        const auto r = validate_bytes({bytes.data(), n}, "t");
        REQUIRE_MESSAGE(!r.valid(), "truncation to " << n << " accepted");
        CHECK(r.to_text().find("t: error: ") == 0);
    }
}

TEST_CASE("validate rejects every single-bit flip of header and section table") {
    const auto good = load(data_dir() / "valid" / "tiny.lsnif");
    for (std::size_t byte = 0; byte < 64 + 5 * 64; ++byte)
        for (int bit = 0; bit < 8; ++bit) {
            auto b = good;
            b[byte] ^= std::uint8_t(1u << bit);
            REQUIRE_MESSAGE(!validate_bytes(b, "f").valid(),
                            "flip of byte " << byte << " bit " << bit << " accepted");
        }
}

TEST_CASE("metadata must agree with the binary descriptor") {
    lsnif_info info{};
    info.grid_resolution = 32;
    info.max_points = 18;
    info.level_count = 2;
    info.level_resolution[0] = 64;
    info.level_resolution[1] = 128;
    info.features_per_level = 3;
    info.log2_table_size = 17;
    info.hidden_layer_count = 1;
    info.hidden_width[0] = 64;
    info.output_count = 5;
    info.distance_encoding = 1;
    info.box_min[0] = -1.5f;
    info.box_max[0] = 0.1f;
    json meta = {{"model",
                  {{"grid_resolution", 32},
                   {"level_resolutions", {64, 128}},
                   {"hidden_widths", {64}},
                   {"distance_encoding", "first_entry_diagonal"},
                   {"ray_inputs", "direction+entry_offsets"}}},
                 {"object", {{"box_min", {-1.5, 0, 0}}, {"box_max", {0.1, 0, 0}}}}};
    CHECK(
        metadata_consistency(meta, info, LSNIF_RAY_INPUT_DIRECTION | LSNIF_RAY_INPUT_ENTRY_OFFSETS).empty());
    meta["model"]["hidden_widths"] = {128};
    meta["object"]["box_max"][0] = 0.2;
    const auto problems = metadata_consistency(meta, info, LSNIF_RAY_INPUT_DIRECTION);
    REQUIRE(problems.size() == 3);
    CHECK(problems[0].find("model.hidden_widths") != std::string::npos);
    CHECK(problems[1].find("model.ray_inputs") != std::string::npos);
    CHECK(problems[2].find("object.box_max") != std::string::npos);
}

TEST_CASE("inspect reports sections, model and metadata; keeps the table of a damaged file") {
    auto bytes = load(data_dir() / "valid" / "unknown_optional_section.lsnif");
    json r = inspect_bytes(bytes, "x");
    REQUIRE(r.contains("model"));
    CHECK(r["sections"].size() == 6);
    CHECK(r["sections"][5]["tag"] == "XTRA");
    CHECK(r["sections"][5]["known"] == false);
    CHECK(r["model"]["input_width"] == 2 * 1 * 2);
    CHECK(r["metadata"]["format"] == "lsnif-metadata/1");
    CHECK_FALSE(r.contains("error"));
    const std::string text = inspect_text(r);
    CHECK(text.find("XTRA") != std::string::npos);
    CHECK(text.find("unknown, skipped") != std::string::npos);

    bytes[r["sections"][3]["offset"].get<std::size_t>()] ^= 4;
    r = inspect_bytes(bytes, "x");
    CHECK(r.contains("error"));
    CHECK(r["sections"][3]["checksum"] == "mismatch");
    CHECK(r["sections"][2]["checksum"] == "ok");
    CHECK_FALSE(r.contains("model"));
}
