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
    InspectReport r = inspect_bytes(bytes, "x");
    REQUIRE(r.model);
    REQUIRE(r.sections.size() == 6);
    CHECK(std::string(r.sections[5].tag) == "XTRA");
    CHECK_FALSE(r.sections[5].known);
    CHECK(r.model->info.input_width == 2 * 1 * 2);
    REQUIRE(r.metadata);
    CHECK((*r.metadata)["format"] == "lsnif-metadata/1");
    CHECK(r.ok());
    const std::string text = inspect_text(r);
    CHECK(text.find("XTRA") != std::string::npos);
    CHECK(text.find("unknown, skipped") != std::string::npos);
    // The JSON writer carries the same facts under the documented keys.
    const json j = inspect_json(r);
    CHECK(j["sections"][5]["tag"] == "XTRA");
    CHECK(j["sections"][5]["known"] == false);
    CHECK(j["model"]["input_width"] == 2 * 1 * 2);
    CHECK(j["model"]["grid"]["encoding"] == "fp16");
    CHECK_FALSE(j["model"]["grid"].contains("levels"));
    CHECK(j["memory"]["file_bytes"] == bytes.size());
    CHECK(j["metadata"]["format"] == "lsnif-metadata/1");
    CHECK_FALSE(j.contains("error"));

    bytes[r.sections[3].offset] ^= 4;
    r = inspect_bytes(bytes, "x");
    REQUIRE(r.error);
    CHECK_FALSE(r.ok());
    REQUIRE(r.sections.size() == 6);
    CHECK_FALSE(r.sections[3].checksum_ok);
    CHECK(r.sections[2].checksum_ok);
    CHECK_FALSE(r.model);
    const json damaged = inspect_json(r);
    CHECK(damaged["sections"][3]["checksum"] == "mismatch");
    CHECK(damaged["error"]["message"] == r.error->message);
    CHECK_FALSE(damaged.contains("model"));
    CHECK(inspect_text(r).find("  error: " + r.error->message) != std::string::npos);
}

TEST_CASE("a quantized grid's dequantization pairs reach validate and inspect alike") {
    const auto bytes = load(data_dir() / "valid" / "quantized_u8.lsnif");
    const ValidationReport v = validate_bytes(bytes, "q");
    REQUIRE(v.valid());
    REQUIRE(v.grid);
    CHECK(v.grid->quantized);
    CHECK(v.grid->encoding == "u8_affine");
    const InspectReport r = inspect_bytes(bytes, "q");
    REQUIRE(r.model);
    REQUIRE(v.grid->levels.size() == r.model->info.level_count);
    REQUIRE(r.model->grid.levels.size() == r.model->info.level_count);
    for (std::size_t l = 0; l < v.grid->levels.size(); ++l) {
        CHECK(v.grid->levels[l].scale > 0);
        CHECK(v.grid->levels[l].scale == r.model->grid.levels[l].scale);
        CHECK(v.grid->levels[l].offset == r.model->grid.levels[l].offset);
    }
    CHECK(v.to_text().find("q: ok\n  format ") == 0);
    CHECK(v.to_text().find(", grid u8_affine: level 0 scale ") != std::string::npos);
    const json j = v.to_json();
    REQUIRE(j["grid"]["levels"].size() == v.grid->levels.size());
    CHECK(j["grid"]["levels"][0]["scale"].get<float>() == v.grid->levels[0].scale);
    CHECK(inspect_json(r)["model"]["grid"] == j["grid"]);
}
