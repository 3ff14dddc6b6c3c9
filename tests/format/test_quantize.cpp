// 8-bit quantized hash grids (FORMAT.md §6.4.1, container version 1.1): the normative
// dequantization, the reference quantizer, the writer's version choice, the C API, and
// bit-exactness of the reader's forward pass against an f32 table dequantized up front.
#include <doctest/doctest.h>

#include "../test_data.hpp"

#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>

#include <bit>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>

using namespace lsnif::format;
namespace fs = std::filesystem;

using lsnif::test::data_dir;
using lsnif::test::load;

namespace {

// A model whose features, weights and sphere-shell occupancy make the network's output
// vary along rays, so a few thousand rays give both hits and misses.
ModelData shell_model(const ModelDesc& d, std::uint32_t seed, float feature_amplitude) {
    auto r = make_empty_model(d);
    REQUIRE(r.ok());
    ModelData m = std::move(r.value());
    const std::uint32_t V = d.grid_resolution;
    const float c = (V - 1) * 0.5f, rad = 0.4f * V;
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const float d2 = (x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c);
                if (d2 <= rad * rad && d2 >= (rad - 2.0f) * (rad - 2.0f)) {
                    const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                    m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
                }
            }
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (std::size_t l = 0; l < m.grid.size(); ++l) {
        const float shift = 0.3f * float(l);  // levels with different ranges and offsets
        for (auto& h : m.grid[l]) h = float_to_half(shift + feature_amplitude * u(rng));
    }
    for (std::uint32_t k = 0; k < d.layer_count(); ++k) {
        const float scale = 2.0f / std::sqrt(float(d.layer_shape(k).second));
        for (auto& h : m.weights[k]) h = float_to_half(scale * u(rng));
        for (auto& h : m.biases[k]) h = float_to_half(0.1f * u(rng));
    }
    return m;
}

ModelDesc exact_desc(std::uint32_t F) {
    ModelDesc d;
    d.grid_resolution = 16;
    d.max_points = 6;
    d.level_resolution = {16, 37};  // one aligned level (4-corner faces), one not
    d.features_per_level = F;       // 3: the unrolled encoder path; others: the generic loop
    d.log2_table_size = 12;         // 17^3 > 4096: both levels hashed
    d.hidden_width = {32, 24};
    d.material_count = 3;
    d.box_min = {-1.0f, -0.75f, -0.5f};
    d.box_max = {1.0f, 0.75f, 0.5f};
    return d;
}

std::vector<lsnif_ray> random_rays(std::size_t n, std::uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    std::vector<lsnif_ray> rays(n);
    for (auto& r : rays) {
        // From a sphere around the box towards a point inside it.
        float o[3] = {u(rng), u(rng), u(rng)};
        const float len = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) + 1e-6f;
        const float target[3] = {0.9f * u(rng), 0.7f * u(rng), 0.45f * u(rng)};
        for (int a = 0; a < 3; ++a) {
            r.org[a] = 3.0f * o[a] / len;
            r.dir[a] = target[a] - r.org[a];
        }
        r.tmin = 0.0f;
        r.tmax = INFINITY;
    }
    return rays;
}

}  // namespace

TEST_CASE("dequantization is one fused multiply-add: the FORMAT.md worked example") {
    // FORMAT.md §6.4.1: scale 0.01f (0x3C23D70A = 0.00999999977648258209228515625), offset
    // -1.0f, q = 200. Exactly, 200 * scale - 1 = 0.99999995529651641845703125; rounded once
    // that is 0x3F7FFFFF = 1 - 2^-24. Rounding the product first (2.0f) would give 1.0f.
    CHECK(std::bit_cast<std::uint32_t>(0.01f) == 0x3C23D70Au);
    CHECK(std::bit_cast<std::uint32_t>(dequantize_u8(200, 0.01f, -1.0f)) == 0x3F7FFFFFu);
    CHECK(dequantize_u8(200, 0.01f, -1.0f) == 1.0f - std::ldexp(1.0f, -24));
    CHECK(std::bit_cast<std::uint32_t>(dequantize_u8(100, 0.01f, -1.0f)) ==
          0xB2C00000u);  // -3 * 2^-27, not 0
    CHECK(std::bit_cast<std::uint32_t>(dequantize_u8(255, 0.01f, -1.0f)) == 0x3FC66666u);
    CHECK(dequantize_u8(0, 0.01f, -1.0f) == -1.0f);
    CHECK(dequantize_u8(77, 0.0f, 0.5f) == 0.5f);  // zero scale: a constant level
    // Against an exact reference: q * scale is exact in double (8 x 24 bits) and, with
    // scale in [2^-9, 2^-8] and |offset| <= 1 a multiple of 2^-48, so is the double sum;
    // one rounding of it to float is the fma.
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (int i = 0; i < 100000; ++i) {
        const float scale = std::ldexp(1.0f + std::fabs(u(rng)), -9);
        const float offset = std::round(u(rng) * 0x1p24f) * 0x1p-24f;
        const auto q = std::uint8_t(rng());
        const double exact = double(q) * scale + double(offset);
        REQUIRE(dequantize_u8(q, scale, offset) == float(exact));
    }
}

TEST_CASE("quantize_level: every value within half a step; the nearest of the 256 levels") {
    std::mt19937 rng(11);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    const std::pair<float, float> ranges[] = {{1e-4f, 0.0f},      {1.0f, 0.0f},   {3.0f, 7.0f},
                                              {250.0f, -1000.0f}, {1e-30f, 1.0f}, {0.0f, 2.5f}};
    for (const auto& [amp, shift] : ranges) {
        std::vector<float> v(5000);
        for (auto& x : v) x = shift + amp * u(rng);
        auto r = quantize_level(v);
        REQUIRE(r.ok());
        const auto& [aff, q] = r.value();
        REQUIRE(q.size() == v.size());
        const float lo = *std::min_element(v.begin(), v.end()), hi = *std::max_element(v.begin(), v.end());
        CHECK(aff.offset == lo);
        CHECK(aff.scale == (hi > lo ? float((double(hi) - lo) / 255.0) : 0.0f));
        for (std::size_t i = 0; i < v.size(); ++i) {
            const float back = dequantize_u8(q[i], aff.scale, aff.offset);
            const double err = std::fabs(double(back) - v[i]);
            // Half a step, plus the f32 roundings of scale (255 steps of it) and of the fma.
            const double slack = 256.0 * std::ldexp(double(aff.scale), -23) +
                                 2.0 * std::ldexp(std::fabs(double(v[i])) + std::fabs(double(lo)), -24);
            REQUIRE_MESSAGE(err <= aff.scale / 2.0 + slack, "amp " << amp << " value " << v[i]);
            // No other byte dequantizes closer (the spec fixes only dequantization, so the
            // writer searches the byte that serves the reader best).
            if (i % 50 == 0)
                for (int c = 0; c < 256; ++c)
                    REQUIRE(std::fabs(double(dequantize_u8(std::uint8_t(c), aff.scale, aff.offset)) - v[i]) >=
                            err);
        }
    }
    // Edges: constant level, one value, range that would overflow 255 * scale + offset.
    auto c = quantize_level(std::vector<float>(10, -3.5f));
    REQUIRE(c.ok());
    CHECK(c->affine.scale == 0.0f);
    CHECK(c->affine.offset == -3.5f);
    const float big = std::numeric_limits<float>::max();
    auto o = quantize_level(std::vector<float>{-big, big});
    REQUIRE(o.ok());
    CHECK(std::isfinite(dequantize_u8(255, o->affine.scale, o->affine.offset)));
    CHECK(quantize_level(std::vector<float>{1.0f, NAN}).error().status == LSNIF_ERR_NONFINITE);
    CHECK(quantize_level(std::vector<float>{}).ok());
}

TEST_CASE("quantized round trip: same bytes, scale and offset; version 1.1 only when quantized") {
    ModelDesc d = exact_desc(2);
    const ModelData fp16 = shell_model(d, 3, 0.5f);
    auto q = quantize_model(fp16);
    REQUIRE_MESSAGE(q.ok(), q.error().message);
    const ModelData& m = q.value();
    CHECK(m.desc.grid_encoding == GridEncoding::u8_affine);
    CHECK(m.grid.empty());
    for (int level : {0, 19}) {
        WriteOptions o;
        o.zstd_level = level;
        auto bytes = serialize(m, o);
        REQUIRE(bytes.ok());
        CHECK(bytes.value()[8] == 1);
        CHECK(bytes.value()[10] == 1);  // 1.1
        auto back = read_model(bytes.value());
        REQUIRE_MESSAGE(back.ok(), back.error().message);
        CHECK(back->version_minor == 1);
        CHECK(back->desc.grid_encoding == GridEncoding::u8_affine);
        CHECK(back->grid.empty());
        CHECK(back->grid_u8 == m.grid_u8);
        REQUIRE(back->grid_affine.size() == m.grid_affine.size());
        for (std::size_t l = 0; l < m.grid_affine.size(); ++l) {
            CHECK(std::bit_cast<std::uint32_t>(back->grid_affine[l].scale) ==
                  std::bit_cast<std::uint32_t>(m.grid_affine[l].scale));
            CHECK(std::bit_cast<std::uint32_t>(back->grid_affine[l].offset) ==
                  std::bit_cast<std::uint32_t>(m.grid_affine[l].offset));
        }
        CHECK(back->weights == m.weights);
        CHECK(serialize(back.value(), o).value() == bytes.value());
        // GRID raw size 8 L + F sum(entries) (FORMAT.md §6.4.1).
        CHECK(d.grid_raw_size() == 2 * 2 * 2 * 4096);
        ModelDesc dq = d;
        dq.grid_encoding = GridEncoding::u8_affine;
        CHECK(dq.grid_raw_size() == 8 * 2 + 2 * 2 * 4096);
        CHECK(dq.parameter_count() == d.parameter_count());
    }
    // The fp16 model is still written as 1.0, whatever version its ModelData says.
    ModelData old = fp16;
    old.version_minor = 1;
    auto b10 = serialize(old);
    REQUIRE(b10.ok());
    CHECK(b10.value()[10] == 0);
    CHECK(b10.value() == serialize(fp16).value());
    // Mixed or inconsistent arrays are refused before anything is written.
    ModelData mixed = m;
    mixed.grid = fp16.grid;
    CHECK(serialize(mixed).error().status == LSNIF_ERR_MODEL);
    ModelData neg = m;
    neg.grid_affine[1].scale = -1.0f;
    CHECK(serialize(neg).error().status == LSNIF_ERR_MODEL);
    ModelData inf = m;
    inf.grid_affine[0] = {1e38f, 1e38f};
    CHECK(serialize(inf).error().status == LSNIF_ERR_NONFINITE);
    CHECK(quantize_model(m).error().status == LSNIF_ERR_INVALID_ARGUMENT);
}

TEST_CASE("the fp16 writer still produces the committed 1.0 bytes") {
    // Read back and written again with the options gen_golden used: byte-identical.
    for (const char* name : {"tiny.lsnif", "v1_default.lsnif"}) {
        const auto bytes = load(data_dir() / "valid" / name);
        CHECK(bytes[10] == 0);
        auto m = read_model(bytes);
        REQUIRE(m.ok());
        CHECK(m->version_minor == 0);
        CHECK(serialize(m.value()).value() == bytes);
    }
    const auto u8 = load(data_dir() / "valid" / "quantized_u8.lsnif");
    auto m = read_model(u8);
    REQUIRE(m.ok());
    CHECK(serialize(m.value()).value() == u8);
    // A 1.1 header on an fp16 grid is read (grid_encoding 0 keeps its 1.0 meaning).
    auto v11 = read_model(load(data_dir() / "valid" / "v1_1_fp16.lsnif"));
    REQUIRE(v11.ok());
    CHECK(v11->version_minor == 1);
    CHECK(v11->desc.grid_encoding == GridEncoding::fp16);
}

TEST_CASE("C API: quantized grid arrays, dequantization pairs, info") {
    const auto bytes = load(data_dir() / "valid" / "quantized_u8.lsnif");
    const auto ref = read_model(bytes);
    REQUIRE(ref.ok());
    lsnif_model* m = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &m, nullptr) == LSNIF_OK);
    lsnif_info info{};
    REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
    CHECK(info.version_minor == 1);
    CHECK(info.grid_encoding == LSNIF_GRID_U8_AFFINE);
    lsnif_array a{};
    for (std::uint32_t l = 0; l < info.level_count; ++l) {
        REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_GRID_LEVEL, l, &a) == LSNIF_OK);
        CHECK(a.dtype == LSNIF_DTYPE_UINT8);
        CHECK(a.rank == 2);
        CHECK(a.dims[0] == info.level_entries[l]);
        CHECK(a.dims[1] == info.features_per_level);
        CHECK(a.bytes == info.level_entries[l] * info.features_per_level);
        CHECK(std::memcmp(a.data, ref->grid_u8[l].data(), a.bytes) == 0);
        REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_GRID_DEQUANT, l, &a) == LSNIF_OK);
        CHECK(a.dtype == LSNIF_DTYPE_FLOAT32);
        CHECK(a.rank == 1);
        CHECK(a.dims[0] == 2);
        CHECK(a.bytes == 8);
        const float* p = static_cast<const float*>(a.data);
        CHECK(p[0] == ref->grid_affine[l].scale);
        CHECK(p[1] == ref->grid_affine[l].offset);
    }
    CHECK(lsnif_get_array(m, LSNIF_ARRAY_GRID_DEQUANT, info.level_count, &a) == LSNIF_ERR_INVALID_ARGUMENT);
    const std::uint64_t u8_bytes = info.decoded_bytes;
    std::size_t u8_meta = 0;
    lsnif_metadata(m, &u8_meta);
    lsnif_close(m);

    // The same model in fp16: no dequantization pairs, and more memory held.
    const auto fp16 = load(data_dir() / "valid" / "v1_1_fp16.lsnif");
    REQUIRE(lsnif_open_memory(fp16.data(), fp16.size(), &m, nullptr) == LSNIF_OK);
    REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
    CHECK(info.grid_encoding == LSNIF_GRID_FP16);
    REQUIRE(lsnif_get_array(m, LSNIF_ARRAY_GRID_LEVEL, 0, &a) == LSNIF_OK);
    CHECK(a.dtype == LSNIF_DTYPE_FLOAT16);
    CHECK(lsnif_get_array(m, LSNIF_ARRAY_GRID_DEQUANT, 0, &a) == LSNIF_ERR_INVALID_ARGUMENT);
    // Same dimensions (tiny_desc: one level of 256 entries x F = 2). The grid is held once,
    // as stored plus grid_tail_pad(F) elements: 2 bytes per value instead of 1, and no
    // (scale, offset) pair (8 bytes). The metadata texts differ in length only.
    REQUIRE(info.level_count == 1);
    REQUIRE(info.features_per_level == 2);
    std::size_t fp16_meta = 0;
    lsnif_metadata(m, &fp16_meta);
    const std::uint64_t values = info.level_entries[0] * 2 + grid_tail_pad(2);
    CHECK(std::int64_t(info.decoded_bytes - u8_bytes) ==
          std::int64_t(values) - 8 + std::int64_t(fp16_meta) - std::int64_t(u8_meta));
    lsnif_close(m);
}

TEST_CASE(
    "lsnif_set_arithmetic: auto picks int8 where AVX-512 VNNI is, else bf16 where AVX-512 BF16 is, fp32 "
    "always works, and the reduced arithmetics stay close to fp32") {
    auto q = quantize_model(shell_model(exact_desc(3), 43, 0.8f));
    REQUIRE(q.ok());
    const auto bytes = serialize(q.value()).value();
    lsnif_model* model = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &model, nullptr) == LSNIF_OK);
    const lsnif_arithmetic bf16 = cpu_features().avx512_bf16 ? LSNIF_ARITHMETIC_BF16 : LSNIF_ARITHMETIC_FP32;
    const lsnif_arithmetic best = cpu_features().avx512_vnni ? LSNIF_ARITHMETIC_INT8 : bf16;
    CHECK(lsnif_get_arithmetic(model) == best);  // what lsnif_open chose
    lsnif_arithmetic in_use{};
    CHECK(lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, &in_use) == LSNIF_OK);
    CHECK(in_use == LSNIF_ARITHMETIC_FP32);
    CHECK(lsnif_get_arithmetic(model) == LSNIF_ARITHMETIC_FP32);
    const auto rays = random_rays(4000, 7);
    std::vector<lsnif_hit> h32(rays.size());
    REQUIRE(lsnif_intersect(model, rays.data(), rays.size(), h32.data()) == LSNIF_OK);
    // Each reduced arithmetic, and what it falls back to on CPUs without its instructions.
    for (const auto& [requested, expected] :
         {std::pair{LSNIF_ARITHMETIC_BF16, bf16}, std::pair{LSNIF_ARITHMETIC_INT8, best}}) {
        const std::string name = lsnif_arithmetic_string(requested);
        CAPTURE(name);
        std::vector<lsnif_hit> h(rays.size());
        CHECK(lsnif_set_arithmetic(model, requested, &in_use) == LSNIF_OK);
        CHECK(in_use == expected);
        CHECK(lsnif_get_arithmetic(model) == expected);
        REQUIRE(lsnif_intersect(model, rays.data(), rays.size(), h.data()) == LSNIF_OK);
        std::size_t agree = 0, both = 0;
        double max_dt = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) {
            agree += h32[i].hit == h[i].hit;
            if (h32[i].hit && h[i].hit)
                ++both, max_dt = std::max(max_dt, double(std::fabs(h32[i].t - h[i].t)));
        }
        MESSAGE(std::string(lsnif_arithmetic_string(in_use))
                << " vs fp32 on a shell model: " << agree << " of " << rays.size() << " hit decisions agree; "
                << both << " common hits, max |dt| " << max_dt);
        CHECK(double(agree) >= 0.99 * double(rays.size()));
        if (expected == LSNIF_ARITHMETIC_FP32) CHECK(agree == rays.size());  // same arithmetic: identical
        // The any-hit query decides exactly as the closest-hit one, also under an instance
        // (scaled by 2, translated): same arithmetic, only the visibility output computed.
        std::vector<std::uint8_t> occ(rays.size(), 7);
        REQUIRE(lsnif_occluded(model, rays.data(), rays.size(), occ.data()) == LSNIF_OK);
        std::size_t same = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) same += occ[i] == h[i].hit;
        CHECK(same == rays.size());
        const float to_world[12] = {2, 0, 0, 0.5f, 0, 2, 0, -1, 0, 0, 2, 3};
        std::vector<lsnif_ray> world(rays);
        for (lsnif_ray& r : world)
            for (int a = 0; a < 3; ++a) r.org[a] = 2 * r.org[a] + to_world[4 * a + 3], r.dir[a] *= 2;
        std::vector<lsnif_hit> wh(rays.size());
        REQUIRE(lsnif_intersect_instance(model, to_world, world.data(), world.size(), wh.data()) == LSNIF_OK);
        REQUIRE(lsnif_occluded_instance(model, to_world, world.data(), world.size(), occ.data()) == LSNIF_OK);
        same = 0;
        std::size_t hits = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) same += occ[i] == wh[i].hit, hits += occ[i];
        CHECK(same == rays.size());
        CHECK(hits > rays.size() / 20);  // the comparison covers hits and misses
        CHECK(hits < rays.size() - rays.size() / 20);
    }
    CHECK(lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_AUTO, &in_use) == LSNIF_OK);
    CHECK(in_use == best);
    CHECK(lsnif_set_arithmetic(model, static_cast<lsnif_arithmetic>(7), nullptr) ==
          LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_arithmetic(model) == best);  // unchanged by the refused call
    CHECK(lsnif_set_arithmetic(nullptr, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_arithmetic(nullptr) == LSNIF_ARITHMETIC_FP32);
    CHECK(std::string(lsnif_arithmetic_string(LSNIF_ARITHMETIC_INT8)) == "int8");
    CHECK(std::string(lsnif_arithmetic_string(LSNIF_ARITHMETIC_AUTO)) == "auto");
    CHECK(std::string(lsnif_arithmetic_string(static_cast<lsnif_arithmetic>(7))) == "unknown");
    lsnif_close(model);
}

TEST_CASE("quantized forward pass is bit-exact with an f32 table dequantized by the normative fma") {
    for (std::uint32_t F : {3u, 2u}) {
        CAPTURE(F);
        auto q = quantize_model(shell_model(exact_desc(F), 40 + F, 0.8f));
        REQUIRE(q.ok());
        const auto bytes = serialize(q.value()).value();
        lsnif_model* model = nullptr;
        REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &model, nullptr) == LSNIF_OK);
        // The reference below runs the MLP in fp32; this test is about the gather.
        REQUIRE(lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_OK);
        const auto rays = random_rays(4000, 100 + F);
        std::vector<lsnif_hit> hits(rays.size());
        REQUIRE(lsnif_intersect(model, rays.data(), rays.size(), hits.data()) == LSNIF_OK);
        lsnif_close(model);

        // Reference: the same file read back, every byte dequantized up front into f32
        // tables, then the same trace / encode / MLP / decode, batched as intersect() does.
        const ModelData m = read_model(bytes).value();
        const Geometry geo = make_geometry(m.desc);
        const OccupancyGrid occ(m.desc.grid_resolution, m.occupancy);
        const Network net = make_network(m);
        const Runtime rt = make_runtime(m);
        const auto u8_views = rt.grid_views();
        std::vector<std::vector<float>> tables;
        std::vector<GridView> f32_views;
        for (std::uint32_t l = 0; l < geo.L; ++l) tables.push_back(dequantize_level(m, l));
        for (const auto& t : tables) f32_views.push_back({t.data(), geo.F, GridElement::f32});
        REQUIRE(u8_views.size() == geo.L);
        CHECK(u8_views[0].element == GridElement::u8);

        constexpr std::size_t kChunk = 256;  // intersect()'s batch, so MLP rows line up
        std::vector<RayPoints> pts(kChunk);
        std::vector<float> input(kChunk * geo.input_width), row(geo.input_width), scratch;
        std::vector<std::uint32_t> which(kChunk);
        std::size_t n_hits = 0, n_inferred = 0;
        for (std::size_t base = 0; base < rays.size(); base += kChunk) {
            const std::size_t n = std::min(kChunk, rays.size() - base);
            std::size_t k = 0;
            for (std::size_t i = 0; i < n; ++i) {
                const Ray& r = reinterpret_cast<const Ray&>(rays[base + i]);
                if (trace_points(geo, occ, r, pts[k]) != TraceStatus::ok) {
                    REQUIRE(hits[base + i].hit == 0);
                    continue;
                }
                float* in = input.data() + k * geo.input_width;
                encode_points(geo, f32_views.data(), pts[k], in);
                // The encoder's rows themselves: u8 gather == f32 table, bit for bit.
                encode_points(geo, u8_views.data(), pts[k], row.data());
                REQUIRE(std::memcmp(row.data(), in, row.size() * sizeof(float)) == 0);
                which[k++] = std::uint32_t(i);
            }
            if (!k) continue;
            n_inferred += k;
            const float* out = mlp_forward(net, input.data(), k, scratch);
            for (std::size_t j = 0; j < k; ++j) {
                const std::size_t i = base + which[j];
                const Hit want = decode_output(geo, pts[j], reinterpret_cast<const Ray&>(rays[i]),
                                               out + j * net.out_padded.back());
                const lsnif_hit& got = hits[i];
                REQUIRE(got.hit == want.hit);
                REQUIRE(got.material == want.material);
                REQUIRE(std::bit_cast<std::uint32_t>(got.t) == std::bit_cast<std::uint32_t>(want.t));
                for (int a = 0; a < 3; ++a)
                    REQUIRE(std::bit_cast<std::uint32_t>(got.normal[a]) ==
                            std::bit_cast<std::uint32_t>(want.normal[a]));
                n_hits += want.hit;
            }
        }
        // The comparison covered real work: many inferred rays, hits and non-hits.
        CHECK(n_inferred > 1000);
        CHECK(n_hits > 200);
        CHECK(n_inferred - n_hits > 50);
    }
}

TEST_CASE("a ray's result does not depend on its batch: rays leaving one point in runs, shuffled or alone") {
    // The reader encodes a run's shared first point once (lsnif.h); whatever the batch,
    // every ray must get the bits it gets alone, in each arithmetic.
    auto q = quantize_model(shell_model(exact_desc(3), 43, 0.8f));
    REQUIRE(q.ok());
    const auto bytes = serialize(q.value()).value();
    lsnif_model* model = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &model, nullptr) == LSNIF_OK);
    const ModelDesc d = exact_desc(3);
    std::mt19937 rng(21);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    std::vector<lsnif_ray> rays;
    for (int o = 0; o < 150; ++o) {  // points in the occupied shell (radius 0.4 V - 1 voxels)
        float dir[3] = {u(rng), u(rng), u(rng)};
        const float len = std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]) + 1e-6f;
        float org[3];
        for (int a = 0; a < 3; ++a) {
            const float V = float(d.grid_resolution), g = (V - 1) * 0.5f + (0.4f * V - 1.0f) * dir[a] / len;
            org[a] = d.box_min[a] + g * (d.box_max[a] - d.box_min[a]) / V;
        }
        for (int k = 0; k < 16; ++k)
            rays.push_back(
                {{org[0], org[1], org[2]}, 0.0f, {u(rng), u(rng), u(rng)}, k % 3 ? INFINITY : 0.3f});
    }
    std::vector<std::size_t> perm(rays.size());
    for (std::size_t i = 0; i < perm.size(); ++i) perm[i] = i;
    std::shuffle(perm.begin(), perm.end(), rng);
    std::vector<lsnif_ray> shuffled(rays.size());
    for (std::size_t i = 0; i < rays.size(); ++i) shuffled[i] = rays[perm[i]];
    for (const lsnif_arithmetic a : {LSNIF_ARITHMETIC_FP32, LSNIF_ARITHMETIC_BF16, LSNIF_ARITHMETIC_INT8}) {
        lsnif_arithmetic in_use{};
        REQUIRE(lsnif_set_arithmetic(model, a, &in_use) == LSNIF_OK);
        CAPTURE(std::string(lsnif_arithmetic_string(in_use)));
        const std::size_t n = rays.size();
        std::vector<lsnif_hit> batch(n), mixed(n), alone(n);
        std::vector<std::uint8_t> occ_batch(n), occ_mixed(n), occ_alone(n);
        REQUIRE(lsnif_intersect(model, rays.data(), n, batch.data()) == LSNIF_OK);
        REQUIRE(lsnif_occluded(model, rays.data(), n, occ_batch.data()) == LSNIF_OK);
        std::vector<lsnif_hit> mixed_order(n);
        std::vector<std::uint8_t> occ_mixed_order(n);
        REQUIRE(lsnif_intersect(model, shuffled.data(), n, mixed_order.data()) == LSNIF_OK);
        REQUIRE(lsnif_occluded(model, shuffled.data(), n, occ_mixed_order.data()) == LSNIF_OK);
        for (std::size_t i = 0; i < n; ++i) {  // back to the rays' order
            mixed[perm[i]] = mixed_order[i];
            occ_mixed[perm[i]] = occ_mixed_order[i];
        }
        for (std::size_t i = 0; i < n; ++i) {
            REQUIRE(lsnif_intersect(model, &rays[i], 1, &alone[i]) == LSNIF_OK);
            REQUIRE(lsnif_occluded(model, &rays[i], 1, &occ_alone[i]) == LSNIF_OK);
        }
        std::size_t same = 0, hits = 0;
        for (std::size_t i = 0; i < n; ++i) {
            same += std::memcmp(&batch[i], &alone[i], sizeof(lsnif_hit)) == 0 &&
                    std::memcmp(&mixed[i], &alone[i], sizeof(lsnif_hit)) == 0 &&
                    occ_batch[i] == occ_alone[i] && occ_mixed[i] == occ_alone[i];
            hits += alone[i].hit;
        }
        CHECK(same == n);
        CHECK(hits > n / 20);  // hits and misses both compared (rays from the shell mostly hit)
        CHECK(n - hits >= 20);
    }
    lsnif_close(model);
}
