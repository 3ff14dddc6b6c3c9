// The resident bytes the C API reports (lsnif_info::decoded_bytes) are exactly what the handle
// holds: this executable replaces the global allocation functions with counting ones, so the
// live bytes after lsnif_open_* minus those before are every allocation the handle kept.
// A binary of its own because the replacement is process-wide.
#include <doctest/doctest.h>

#include "../test_data.hpp"

#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>

#include <atomic>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <new>
#include <thread>
#include <vector>

namespace {

std::atomic<std::int64_t> g_live{0};

// Each block starts with a header of `kHeader` bytes holding the requested size, so a
// delete without a size still knows what it frees. kHeader keeps any alignment up to it.
constexpr std::size_t kHeader = 64;

void* counted_alloc(std::size_t n, std::size_t align) {
    const std::size_t head = align > kHeader ? align : kHeader;
    void* base = std::aligned_alloc(head, ((n + head + head - 1) / head) * head);
    if (!base) return nullptr;
    auto* p = static_cast<unsigned char*>(base) + head;
    reinterpret_cast<std::size_t*>(p)[-1] = n;
    reinterpret_cast<std::size_t*>(p)[-2] = head;
    g_live += std::int64_t(n);
    return p;
}

void counted_free(void* p) noexcept {
    if (!p) return;
    auto* q = static_cast<unsigned char*>(p);
    const std::size_t n = reinterpret_cast<std::size_t*>(q)[-1];
    const std::size_t head = reinterpret_cast<std::size_t*>(q)[-2];
    g_live -= std::int64_t(n);
    std::free(q - head);
}

}  // namespace

void* operator new(std::size_t n) {
    if (void* p = counted_alloc(n, alignof(std::max_align_t))) return p;
    throw std::bad_alloc();
}
void* operator new[](std::size_t n) {
    return operator new(n);
}
void* operator new(std::size_t n, const std::nothrow_t&) noexcept {
    return counted_alloc(n, alignof(std::max_align_t));
}
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept {
    return counted_alloc(n, alignof(std::max_align_t));
}
void* operator new(std::size_t n, std::align_val_t a) {
    if (void* p = counted_alloc(n, std::size_t(a))) return p;
    throw std::bad_alloc();
}
void* operator new[](std::size_t n, std::align_val_t a) {
    return operator new(n, a);
}
void* operator new(std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
    return counted_alloc(n, std::size_t(a));
}
void* operator new[](std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
    return counted_alloc(n, std::size_t(a));
}
void operator delete(void* p) noexcept {
    counted_free(p);
}
void operator delete[](void* p) noexcept {
    counted_free(p);
}
void operator delete(void* p, std::size_t) noexcept {
    counted_free(p);
}
void operator delete[](void* p, std::size_t) noexcept {
    counted_free(p);
}
void operator delete(void* p, std::align_val_t) noexcept {
    counted_free(p);
}
void operator delete[](void* p, std::align_val_t) noexcept {
    counted_free(p);
}
void operator delete(void* p, std::size_t, std::align_val_t) noexcept {
    counted_free(p);
}
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept {
    counted_free(p);
}

namespace {

struct Opened {
    lsnif_model* model = nullptr;
    std::int64_t held = 0;  // live bytes the open added
};

Opened open_counted(const std::vector<std::uint8_t>& bytes) {
    Opened o;
    const std::int64_t before = g_live.load();
    lsnif_error err{};
    REQUIRE_MESSAGE(lsnif_open_memory(bytes.data(), bytes.size(), &o.model, &err) == LSNIF_OK, err.message);
    o.held = g_live.load() - before;
    return o;
}

// The golden assets of tests/data/valid: every format version, grid encoding and ray input.
std::vector<std::filesystem::path> golden_assets() {
    std::vector<std::filesystem::path> out;
    for (const auto& entry : std::filesystem::directory_iterator(lsnif::test::data_dir() / "valid"))
        if (entry.path().extension() == ".lsnif") out.push_back(entry.path());
    REQUIRE(out.size() >= 5);
    return out;
}

// A golden asset's bytes and its model as read_model gives it.
struct Golden {
    std::vector<std::uint8_t> bytes;
    lsnif::format::ModelData model;
};
Golden read_golden(const std::filesystem::path& path) {
    Golden g{lsnif::test::load(path), {}};
    auto model = lsnif::format::read_model(g.bytes);
    REQUIRE(model.ok());
    g.model = std::move(model.value());
    return g;
}

std::uint64_t decoded_bytes(const lsnif_model* m) {
    lsnif_info info{};
    REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
    return info.decoded_bytes;
}

}  // namespace

TEST_CASE("decoded_bytes is every byte the handle holds, for each golden asset and arithmetic") {
    for (const auto& path : golden_assets()) {
        CAPTURE(path.filename().string());
        const auto bytes = lsnif::test::load(path);
        Opened o = open_counted(bytes);
        CHECK(o.held > 0);
        CHECK(std::uint64_t(o.held) == decoded_bytes(o.model));
        // Each arithmetic packs the network its own way; what the handle then holds changes
        // with it, and decoded_bytes follows.
        for (const lsnif_arithmetic a :
             {LSNIF_ARITHMETIC_FP32, LSNIF_ARITHMETIC_BF16, LSNIF_ARITHMETIC_INT8}) {
            CAPTURE(lsnif_arithmetic_string(a));
            const std::int64_t before = g_live.load();
            const std::uint64_t reported_before = decoded_bytes(o.model);
            REQUIRE(lsnif_set_arithmetic(o.model, a, nullptr) == LSNIF_OK);
            CHECK(std::int64_t(decoded_bytes(o.model)) - std::int64_t(reported_before) ==
                  g_live.load() - before);
        }
        const std::int64_t before_close = g_live.load();
        const std::uint64_t last = decoded_bytes(o.model);
        lsnif_close(o.model);
        CHECK(before_close - g_live.load() == std::int64_t(last));
    }
}

TEST_CASE("format::resident_bytes predicts what a handle holds with the fp32 network") {
    for (const auto& path : golden_assets()) {
        CAPTURE(path.filename().string());
        const Golden g = read_golden(path);
        Opened o = open_counted(g.bytes);
        REQUIRE(lsnif_set_arithmetic(o.model, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_OK);
        CHECK(lsnif::format::resident_bytes(g.model) == decoded_bytes(o.model));
        lsnif_close(o.model);
    }
}

// What the fp32 handle may hold besides the feature tables: the occupancy at 2 bits per
// voxel, every weight once in fp16 (W^T, outputs padded to 16), the output layer also in
// fp32 and the biases in fp32; `slack` covers the handle, the descriptor and the metadata.
std::uint64_t fp32_bound(const lsnif_info& info, std::size_t metadata_bytes) {
    const auto pad16 = [](std::uint64_t n) { return (n + 15) / 16 * 16; };
    const std::uint64_t element = info.grid_encoding == LSNIF_GRID_U8_AFFINE ? 1 : 2;
    std::uint64_t n = 0;
    for (std::uint32_t l = 0; l < info.level_count; ++l)
        n += (info.level_entries[l] * info.features_per_level + 4) * element;
    const std::uint64_t S = (info.grid_resolution + 1) / 2;
    n += (S * S * S + 1) * 2;
    std::uint64_t in = info.input_width;
    for (std::uint32_t k = 0; k <= info.hidden_layer_count; ++k) {
        const std::uint64_t out = k < info.hidden_layer_count ? info.hidden_width[k] : info.output_count;
        n += in * pad16(out) * 2 + pad16(out) * 4;
        if (k == info.hidden_layer_count) n += in * pad16(out) * 4;
        in = out;
    }
    constexpr std::uint64_t slack = 4096;
    return n + metadata_bytes + slack;
}

TEST_CASE("fp32 holds the least: each weight once in fp16, the occupancy at 2 bits per voxel") {
    for (const auto& path : golden_assets()) {
        CAPTURE(path.filename().string());
        Opened o = open_counted(lsnif::test::load(path));
        REQUIRE(lsnif_set_arithmetic(o.model, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_OK);
        lsnif_info info{};
        REQUIRE(lsnif_get_info(o.model, &info) == LSNIF_OK);
        std::size_t metadata = 0;
        lsnif_metadata(o.model, &metadata);
        CHECK(info.decoded_bytes <= fp32_bound(info, metadata + 1));
        for (const lsnif_arithmetic a : {LSNIF_ARITHMETIC_BF16, LSNIF_ARITHMETIC_INT8}) {
            lsnif_arithmetic in_use{};
            REQUIRE(lsnif_set_arithmetic(o.model, a, &in_use) == LSNIF_OK);
            CAPTURE(lsnif_arithmetic_string(in_use));
            CHECK(decoded_bytes(o.model) >= info.decoded_bytes);
        }
        lsnif_close(o.model);
    }
}

TEST_CASE("lsnif_get_array builds the file's occupancy, weights and biases once, exactly, and counts them") {
    for (const auto& path : golden_assets()) {
        CAPTURE(path.filename().string());
        const Golden g = read_golden(path);
        Opened o = open_counted(g.bytes);
        // Whichever arithmetic the network runs in, the arrays are the file's.
        REQUIRE(lsnif_set_arithmetic(o.model, LSNIF_ARITHMETIC_INT8, nullptr) == LSNIF_OK);
        const std::uint32_t layers = lsnif_layer_count(o.model);
        // Several threads ask at once; each must see the finished arrays.
        std::vector<std::thread> threads;
        threads.reserve(4);
        std::atomic<int> mismatches{0};
        const std::int64_t live_before = g_live.load();
        const std::uint64_t reported_before = decoded_bytes(o.model);
        for (int t = 0; t < 4; ++t)
            threads.emplace_back([&] {
                lsnif_array a{};
                if (lsnif_get_array(o.model, LSNIF_ARRAY_OCCUPANCY, 0, &a) != LSNIF_OK ||
                    a.bytes != g.model.occupancy.size() ||
                    std::memcmp(a.data, g.model.occupancy.data(), a.bytes) != 0)
                    ++mismatches;
                for (std::uint32_t k = 0; k < layers; ++k) {
                    if (lsnif_get_array(o.model, LSNIF_ARRAY_LAYER_WEIGHTS, k, &a) != LSNIF_OK ||
                        a.bytes != g.model.weights[k].size() * 2 ||
                        std::memcmp(a.data, g.model.weights[k].data(), a.bytes) != 0)
                        ++mismatches;
                    if (lsnif_get_array(o.model, LSNIF_ARRAY_LAYER_BIAS, k, &a) != LSNIF_OK ||
                        a.bytes != g.model.biases[k].size() * 2 ||
                        std::memcmp(a.data, g.model.biases[k].data(), a.bytes) != 0)
                        ++mismatches;
                }
            });
        for (auto& t : threads) t.join();
        threads.clear();
        CHECK(mismatches.load() == 0);
        const std::int64_t grown = g_live.load() - live_before;
        CHECK(grown > 0);
        CHECK(std::int64_t(decoded_bytes(o.model)) - std::int64_t(reported_before) == grown);
        // Built once: asking again allocates nothing.
        lsnif_array a{};
        REQUIRE(lsnif_get_array(o.model, LSNIF_ARRAY_LAYER_WEIGHTS, 0, &a) == LSNIF_OK);
        CHECK(g_live.load() - live_before == grown);
        lsnif_close(o.model);
    }
}
