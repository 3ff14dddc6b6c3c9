// Container reader/writer: round trips, checksums, fp16, and rejection of damaged input.
#include <doctest/doctest.h>

#include "../test_data.hpp"

#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/half.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>

#include <unistd.h>

using namespace lsnif::format;
namespace fs = std::filesystem;

using lsnif::test::data_dir;
using lsnif::test::load;

namespace {

ModelData random_model(const ModelDesc& d, std::uint32_t seed) {
    auto r = make_empty_model(d);
    REQUIRE(r.ok());
    ModelData m = std::move(r.value());
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (auto& b : m.occupancy) b = std::uint8_t(rng());
    const std::uint64_t bits = d.voxel_count();
    if (bits % 8) m.occupancy.back() &= std::uint8_t((1u << (bits % 8)) - 1);
    for (auto& l : m.grid)
        for (auto& h : l) h = float_to_half(u(rng) * 1e-3f);
    for (auto& w : m.weights)
        for (auto& h : w) h = float_to_half(u(rng));
    for (auto& b : m.biases)
        for (auto& h : b) h = float_to_half(u(rng));
    m.metadata_json = "{\"seed\": " + std::to_string(seed) + ", \"name\": \"caf\xC3\xA9\"}";
    return m;
}

ModelDesc small_desc() {
    ModelDesc d;
    d.grid_resolution = 5;
    d.max_points = 3;
    d.level_resolution = {5, 10};
    d.features_per_level = 2;
    d.log2_table_size = 9;
    d.hidden_width = {12, 7};
    d.material_count = 3;
    d.box_min = {-2.f, 0.f, 1.f};
    d.box_max = {2.f, 0.5f, 1.001f};
    return d;
}

}  // namespace

TEST_CASE("crc32c matches the Castagnoli check value") {
    const char* s = "123456789";
    CHECK(crc32c(s, 9) == 0xE3069283u);
    CHECK(crc32c(s, 4, crc32c(s, 0)) == crc32c(s, 4));
    // Incremental equals one-shot across the slicing boundary.
    std::vector<std::uint8_t> buf(1000);
    for (std::size_t i = 0; i < buf.size(); ++i) buf[i] = std::uint8_t(i * 7 + 3);
    CHECK(crc32c(buf.data() + 13, 987, crc32c(buf.data(), 13)) == crc32c(buf.data(), 1000));
}

TEST_CASE("fp16 conversion is exact for every half and rounds to nearest even") {
    for (std::uint32_t h = 0; h < 0x10000; ++h) {
        if (!half_is_finite(std::uint16_t(h))) continue;
        const float f = half_to_float(std::uint16_t(h));
        REQUIRE(float_to_half(f) == h);
    }
    CHECK(half_to_float(0x3C00) == 1.0f);
    CHECK(half_to_float(0xC000) == -2.0f);
    CHECK(half_to_float(0x0001) == std::ldexp(1.0f, -24));  // smallest subnormal
    CHECK(half_to_float(0x7BFF) == 65504.0f);
    CHECK(float_to_half(65520.0f) == 0x7C00);                          // rounds up to Inf
    CHECK(float_to_half(1.0f + std::ldexp(1.0f, -11)) == 0x3C00);      // tie -> even (down)
    CHECK(float_to_half(1.0f + 3 * std::ldexp(1.0f, -11)) == 0x3C02);  // tie -> even (up)
    CHECK(float_to_half(std::ldexp(1.0f, -25)) == 0x0000);             // tie between 0 and min subnormal
    CHECK(float_to_half(std::ldexp(1.5f, -25)) == 0x0001);
    CHECK(std::isnan(half_to_float(float_to_half(NAN))));
}

TEST_CASE("round trip: write, read, identical dimensions, metadata and weights") {
    for (std::uint32_t seed : {1u, 2u, 3u}) {
        ModelDesc d = small_desc();
        if (seed == 2) d.distance_encoding = LSNIF_DISTANCE_SEGMENT, d.material_count = 0;
        if (seed == 3) d.level_resolution = {4, 9, 31}, d.hidden_width = {5};
        const ModelData m = random_model(d, seed);
        for (int level : {0, 3, 19}) {
            WriteOptions o;
            o.zstd_level = level;
            auto bytes = serialize(m, o);
            REQUIRE(bytes.ok());
            auto back = read_model(bytes.value());
            REQUIRE_MESSAGE(back.ok(), back.error().message);
            const ModelData& r = back.value();
            CHECK(r.desc.grid_resolution == d.grid_resolution);
            CHECK(r.desc.level_resolution == d.level_resolution);
            CHECK(r.desc.hidden_width == d.hidden_width);
            CHECK(r.desc.material_count == d.material_count);
            CHECK(r.desc.distance_encoding == d.distance_encoding);
            CHECK(r.desc.box_min == d.box_min);
            CHECK(r.desc.box_max == d.box_max);
            CHECK(r.desc.hash_primes == d.hash_primes);
            CHECK(r.metadata_json == m.metadata_json);
            CHECK(r.occupancy == m.occupancy);
            CHECK(r.grid == m.grid);
            CHECK(r.weights == m.weights);
            CHECK(r.biases == m.biases);
            // Deterministic writer: same input, same bytes.
            CHECK(serialize(m, o).value() == bytes.value());
        }
    }
}

TEST_CASE("ray inputs are written as 1.2 and read back; without them the file stays 1.0") {
    for (const std::uint32_t bits : {0u, kRayInputDirection, kRayInputEntryOffsets, kRayInputsKnown}) {
        ModelDesc d = small_desc();
        d.ray_inputs = bits;
        CHECK(d.input_width() == d.max_points * d.level_count() * d.features_per_level +
                                     (bits & kRayInputDirection ? 3 : 0) +
                                     (bits & kRayInputEntryOffsets ? d.max_points : 0));
        const ModelData m = random_model(d, 11);
        CHECK(m.weights[0].size() == std::size_t(d.hidden_width[0]) * d.input_width());
        auto bytes = serialize(m);
        REQUIRE(bytes.ok());
        CHECK(bytes.value()[10] == (bits ? 2 : 0));  // header version_minor
        auto back = read_model(bytes.value());
        REQUIRE_MESSAGE(back.ok(), back.error().message);
        CHECK(back.value().desc.ray_inputs == bits);
        CHECK(back.value().version_minor == (bits ? 2 : 0));
        CHECK(back.value().weights == m.weights);
    }
    // The C API reports them; older files have none.
    for (const auto& [file, want] :
         {std::pair{"ray_inputs.lsnif", kRayInputsKnown}, std::pair{"quantized_u8.lsnif", 0u},
          std::pair{"v1_default.lsnif", 0u}}) {
        const auto bytes = load(data_dir() / "valid" / file);
        lsnif_model* m = nullptr;
        REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &m, nullptr) == LSNIF_OK);
        std::uint32_t got = 99;
        CHECK(lsnif_get_ray_inputs(m, &got) == LSNIF_OK);
        CHECK_MESSAGE(got == want, file);
        lsnif_info info{};
        REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
        CHECK(info.input_width == info.max_points * info.level_count * info.features_per_level +
                                      (got & LSNIF_RAY_INPUT_DIRECTION ? 3 : 0) +
                                      (got & LSNIF_RAY_INPUT_ENTRY_OFFSETS ? info.max_points : 0));
        lsnif_close(m);
    }
}

TEST_CASE("dense vs hashed level sizes follow the (res+1)^3 <= T rule") {
    ModelDesc d = small_desc();
    d.log2_table_size = 9;        // T = 512
    d.level_resolution = {7, 8};  // 8^3 = 512 dense, 9^3 = 729 hashed
    CHECK(d.level_dense(0));
    CHECK(d.level_entries(0) == 512);
    CHECK_FALSE(d.level_dense(1));
    CHECK(d.level_entries(1) == 512);
    ModelDesc v1;  // defaults: 108 -> 128 -> 128 -> 5
    CHECK(v1.input_width() == 108);
    CHECK(v1.parameter_count() == 2 * (1u << 17) * 3 + (108 * 128 + 128) + (128 * 128 + 128) + (128 * 5 + 5));
}

TEST_CASE("write_file is atomic: the target appears complete and no temporary remains") {
    const fs::path dir = fs::temp_directory_path() / ("lsnif_atomic_" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir);
    const ModelData m = random_model(small_desc(), 9);
    const std::string path = (dir / "a.lsnif").string();
    REQUIRE_FALSE(write_file(path, m));
    CHECK(read_model(load(path)).ok());
    // Overwrite keeps a valid file at every moment: the old one until the rename.
    REQUIRE_FALSE(write_file(path, random_model(small_desc(), 10)));
    CHECK(std::distance(fs::directory_iterator(dir), fs::directory_iterator{}) == 1);
    // A write that cannot happen leaves nothing behind and says where.
    Error e = write_file((dir / "missing" / "b.lsnif").string(), m);
    CHECK(e.status == LSNIF_ERR_IO);
    CHECK(e.message.find("missing") != std::string::npos);
    // An invalid model is refused before any file is created.
    ModelData bad = m;
    bad.weights[0][0] = 0x7E00;
    e = write_file((dir / "c.lsnif").string(), bad);
    CHECK(e.status == LSNIF_ERR_NONFINITE);
    CHECK_FALSE(fs::exists(dir / "c.lsnif"));
    CHECK(std::distance(fs::directory_iterator(dir), fs::directory_iterator{}) == 1);
    fs::remove_all(dir);
}

TEST_CASE("every truncation of a valid file is rejected") {
    const auto bytes = load(data_dir() / "valid" / "tiny.lsnif");
    REQUIRE(read_model(bytes).ok());
    for (std::size_t n = 0; n < bytes.size(); ++n) {
        std::span<const std::uint8_t> cut(bytes.data(), n);
        auto r = read_model(cut);
        REQUIRE_MESSAGE(!r.ok(), "truncation to " << n << " bytes accepted");
        CHECK_FALSE(scan(cut).ok());
        lsnif_model* m = nullptr;
        CHECK(lsnif_open_memory(cut.data(), cut.size(), &m, nullptr) != LSNIF_OK);
        CHECK(m == nullptr);
    }
}

TEST_CASE("every single-bit flip of header and section table is rejected") {
    const auto good = load(data_dir() / "valid" / "tiny.lsnif");
    const std::size_t table_end = 64 + 64 * 5;
    for (std::size_t byte = 0; byte < table_end; ++byte)
        for (int bit = 0; bit < 8; ++bit) {
            auto b = good;
            b[byte] ^= std::uint8_t(1u << bit);
            auto r = read_model(b);
            REQUIRE_MESSAGE(!r.ok(), "flip of byte " << byte << " bit " << bit << " accepted");
        }
}

TEST_CASE("single-bit flips anywhere in the payloads are rejected") {
    for (const char* name : {"tiny.lsnif", "dense_uncompressed.lsnif"}) {
        const auto good = load(data_dir() / "valid" / name);
        // Every bit of these small files: the payload area is covered by the CRCs.
        for (std::size_t byte = 64 * 6; byte < good.size(); ++byte)
            for (int bit = 0; bit < 8; ++bit) {
                auto b = good;
                b[byte] ^= std::uint8_t(1u << bit);
                REQUIRE_MESSAGE(!read_model(b).ok(), name << ": flip of byte " << byte << " accepted");
            }
    }
}

TEST_CASE("golden valid files open; invalid files fail with their status") {
    for (const auto& e : fs::directory_iterator(data_dir() / "valid")) {
        auto r = read_model(load(e.path()));
        CHECK_MESSAGE(r.ok(), e.path() << ": " << (r.ok() ? "" : r.error().message));
    }
    std::size_t invalid = 0;
    for (const auto& e : fs::directory_iterator(data_dir() / "invalid")) {
        if (e.path().extension() != ".lsnif") continue;
        ++invalid;
        auto r = read_model(load(e.path()));
        // Metadata problems are the validator's job; the reader accepts those files.
        const bool meta_only = e.path().filename().string().rfind("metadata_", 0) == 0 &&
                               e.path().filename() != "metadata_nul.lsnif" &&
                               e.path().filename() != "metadata_truncated.lsnif";
        CHECK_MESSAGE(r.ok() == meta_only, e.path());
    }
    CHECK(invalid >= 30);
}

TEST_CASE("C API: open, info, arrays, metadata, status strings, bad arguments") {
    const auto bytes = load(data_dir() / "valid" / "v1_default.lsnif");
    lsnif_model* m = nullptr;
    lsnif_error err{};
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &m, &err) == LSNIF_OK);
    lsnif_info info{};
    REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
    CHECK(info.grid_resolution == 32);
    CHECK(info.max_points == 18);
    CHECK(info.level_count == 2);
    CHECK(info.level_resolution[0] == 64);
    CHECK(info.level_resolution[1] == 128);
    CHECK(info.level_dense[0] == 0);
    CHECK(info.input_width == 108);
    CHECK(info.hidden_layer_count == 2);
    CHECK(info.output_count == 5);
    CHECK(info.file_size == bytes.size());
    CHECK(lsnif_layer_count(m) == 3);
    lsnif_array a{};
    REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_LAYER_WEIGHTS, 0, &a) == LSNIF_OK);
    CHECK(a.dims[0] == 128);
    CHECK(a.dims[1] == 108);
    CHECK(a.bytes == 128 * 108 * 2);
    REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_GRID_LEVEL, 1, &a) == LSNIF_OK);
    CHECK(a.dims[0] == (1u << 17));
    CHECK(a.dims[1] == 3);
    REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_OCCUPANCY, 0, &a) == LSNIF_OK);
    CHECK(a.bytes == 32 * 32 * 32 / 8);
    CHECK(lsnif_get_array(m, LSNIF_ARRAY_LAYER_BIAS, 3, &a) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_array(m, LSNIF_ARRAY_OCCUPANCY, 1, &a) == LSNIF_ERR_INVALID_ARGUMENT);
    std::size_t len = 0;
    const char* meta = lsnif_metadata(m, &len);
    REQUIRE(meta != nullptr);
    CHECK(std::strlen(meta) == len);
    lsnif_close(m);

    CHECK(lsnif_open_memory(nullptr, 10, &m, &err) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_open_file("/nonexistent/x.lsnif", &m, &err) == LSNIF_ERR_IO);
    CHECK(std::string(err.message).find("/nonexistent/x.lsnif") != std::string::npos);
    CHECK(lsnif_open_file(LSNIF_TEST_DATA_DIR, &m, &err) == LSNIF_ERR_IO);  // a directory
    CHECK(lsnif_get_info(nullptr, &info) == LSNIF_ERR_INVALID_ARGUMENT);
    lsnif_close(nullptr);
    for (int s = 0; s <= LSNIF_ERR_INTERNAL; ++s)
        CHECK(std::string(lsnif_status_string(lsnif_status(s))) != "unknown status");
    CHECK(std::string(lsnif_status_string(LSNIF_ERR_VERSION_NEWER)).find("upgrade") != std::string::npos);
    CHECK(std::string(lsnif_status_string(LSNIF_ERR_VERSION_OLDER)).find("re-convert") != std::string::npos);
}

TEST_CASE("every C API call follows its documented NULL rule") {
    auto bytes = load(data_dir() / "valid" / "v1_default.lsnif");
    lsnif_model* m = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &m, nullptr) == LSNIF_OK);
    lsnif_array a{};
    lsnif_ray ray{{0, 0, 0}, 0, {1, 0, 0}, 1};
    lsnif_hit hit{};
    const float identity[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
    lsnif_model* out = m;
    CHECK(lsnif_open_memory(bytes.data(), bytes.size(), nullptr, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_open_memory(nullptr, 0, &out, nullptr) != LSNIF_OK);  // empty input: not a file
    CHECK(out == nullptr);                                            // *out cleared on failure
    CHECK(lsnif_open_file(nullptr, &out, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_open_file("x.lsnif", nullptr, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_info(m, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    std::uint32_t ray_inputs = 0;
    CHECK(lsnif_get_ray_inputs(nullptr, &ray_inputs) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_ray_inputs(m, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_array(nullptr, LSNIF_ARRAY_OCCUPANCY, 0, &a) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_array(m, LSNIF_ARRAY_OCCUPANCY, 0, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_layer_count(nullptr) == 0);
    std::size_t len = 7;
    CHECK(lsnif_metadata(nullptr, &len) == nullptr);
    CHECK(len == 0);
    CHECK(lsnif_metadata(m, nullptr) != nullptr);
    CHECK(lsnif_intersect(nullptr, &ray, 1, &hit) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect(m, nullptr, 1, &hit) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect(m, &ray, 1, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect(m, nullptr, 0, nullptr) == LSNIF_OK);
    CHECK(lsnif_intersect_instance(m, nullptr, &ray, 1, &hit) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect_instance(nullptr, identity, &ray, 1, &hit) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect_instance(m, identity, nullptr, 0, nullptr) == LSNIF_OK);
    std::uint8_t occluded = 7;
    CHECK(lsnif_occluded(nullptr, &ray, 1, &occluded) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded(m, nullptr, 1, &occluded) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded(m, &ray, 1, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded(m, nullptr, 0, nullptr) == LSNIF_OK);
    CHECK(lsnif_occluded_instance(m, nullptr, &ray, 1, &occluded) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded_instance(nullptr, identity, &ray, 1, &occluded) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded_instance(m, identity, &ray, 1, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_occluded_instance(m, identity, nullptr, 0, nullptr) == LSNIF_OK);
    CHECK(occluded == 7);  // refused calls write nothing
    std::uint32_t count = 9;
    CHECK(lsnif_scan_memory(nullptr, 4, nullptr, nullptr, 0, &count, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_scan_memory(bytes.data(), bytes.size(), nullptr, nullptr, 1, &count, nullptr) ==
          LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_scan_memory(bytes.data(), bytes.size(), nullptr, nullptr, 0, nullptr, nullptr) == LSNIF_OK);
    CHECK(std::string(lsnif_status_string(lsnif_status(1000))) == "unknown status");
    lsnif_close(m);
}

TEST_CASE("the runtime version matches the header this program was built with") {
    std::uint32_t major = 0, minor = 99;
    const char* release = lsnif_version(&major, &minor);
    REQUIRE(release != nullptr);
    CHECK(major == LSNIF_VERSION_MAJOR);
    CHECK(minor == LSNIF_VERSION_MINOR);
    CHECK(std::string(release).find('.') != std::string::npos);  // "MAJOR.MINOR.PATCH"
    CHECK(std::string(lsnif_version(nullptr, nullptr)) == release);
}

TEST_CASE("scan reports every section and its checksum state") {
    auto bytes = load(data_dir() / "valid" / "unknown_optional_section.lsnif");
    lsnif_header_info h{};
    lsnif_section_info s[8];
    std::uint32_t count = 0;
    REQUIRE(lsnif_scan_memory(bytes.data(), bytes.size(), &h, s, 8, &count, nullptr) == LSNIF_OK);
    REQUIRE(count == 6);
    CHECK(std::string(s[0].tag) == "META");
    CHECK(std::string(s[5].tag) == "XTRA");
    CHECK(s[5].known == 0);
    CHECK((s[5].flags & LSNIF_SECTION_REQUIRED) == 0);
    for (auto& si : s) (void)si;
    // Damage the GRID payload: the scan still lists all sections, flags the bad one.
    const std::uint64_t grid_off = s[3].offset;
    bytes[grid_off + 1] ^= 1;
    lsnif_error err{};
    CHECK(lsnif_scan_memory(bytes.data(), bytes.size(), &h, s, 8, &count, &err) == LSNIF_ERR_CHECKSUM);
    CHECK(count == 6);
    CHECK(s[3].checksum_ok == 0);
    CHECK(s[2].checksum_ok == 1);
    CHECK(std::string(err.message).find("GRID") != std::string::npos);
}

TEST_CASE("declared sizes never drive allocation: absurd sizes are limits, not OOM") {
    auto bytes = load(data_dir() / "invalid" / "section_too_large.lsnif");
    auto r = read_model(bytes);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error().status == LSNIF_ERR_LIMIT);
}
