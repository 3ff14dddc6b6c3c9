// bf16 / AMX path of the trainer: rounding and packing helpers against scalar definitions,
// the AMX GEMM against a double-precision reference on ragged shapes, and the bf16 training
// step against the fp32 one. Tests that need AMX are skipped (with a message) without it.
#include <doctest/doctest.h>

#include "amx.hpp"
#include "kernels.hpp"

#include <lsnif/analytic/spheres.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <cmath>
#include <cstring>
#include <random>
#include <thread>

using namespace lsnif;
using namespace lsnif::trainer;
using namespace lsnif::analytic;
using namespace lsnif::samples;
using namespace lsnif::trainer::detail;

namespace {

float from_bits(std::uint32_t u) {
    float x;
    std::memcpy(&x, &u, 4);
    return x;
}

std::vector<float> random_matrix(std::size_t rows, std::size_t cols, std::mt19937& rng) {
    std::uniform_real_distribution<float> u(-1.0f, 1.0f);
    std::vector<float> m(rows * cols);
    for (float& x : m) x = u(rng);
    return m;
}

// The cases that need bf16 instructions run as CTest tests of their own, which CTest skips
// on CPUs without them (tests/isa_required.sh, tests/CMakeLists.txt): here, their absence
// is a failure, not a silent pass.
void require_amx() {
    REQUIRE_MESSAGE(amx_available(),
                    "AMX (amx-tile, amx-bf16, avx512-bf16 with OS permission) not available");
}

void require_bf16() {
    REQUIRE_MESSAGE(bf16_backend() != Bf16Backend::none, "no bf16 backend (AMX or AVX-512 BF16)");
}

// Every bf16 GEMM kernel this machine can run: AMX machines also have AVX-512 BF16.
std::vector<Bf16Backend> usable_backends() {
    switch (bf16_backend()) {
        case Bf16Backend::amx: return {Bf16Backend::amx, Bf16Backend::avx512_bf16};
        case Bf16Backend::avx512_bf16: return {Bf16Backend::avx512_bf16};
        case Bf16Backend::none: return {};
    }
    return {};
}

}  // namespace

TEST_CASE("fp32 -> bf16 rounds to nearest even like VCVTNEPS2BF16") {
    CHECK(to_bf16(1.0f) == 0x3f80);
    CHECK(to_bf16(-2.0f) == 0xc000);
    CHECK(to_bf16(from_bits(0x3f808000)) == 0x3f80);  // tie, even below
    CHECK(to_bf16(from_bits(0x3f818000)) == 0x3f82);  // tie, even above
    CHECK(to_bf16(from_bits(0x3f808001)) == 0x3f81);  // above the tie
    CHECK(to_bf16(from_bits(0x3f807fff)) == 0x3f80);  // below the tie
    CHECK(to_bf16(from_bits(0x7f7fffff)) == 0x7f80);  // FLT_MAX rounds to +inf
    CHECK(to_bf16(INFINITY) == 0x7f80);
    CHECK(to_bf16(-INFINITY) == 0xff80);
    CHECK(std::isnan(from_bf16(to_bf16(NAN))));
    CHECK(std::isnan(from_bf16(to_bf16(from_bits(0x7f800001)))));  // signalling NaN stays NaN
    CHECK(to_bf16(from_bits(0x00000123)) == 0x0000);               // subnormal -> signed zero
    CHECK(to_bf16(from_bits(0x80400000)) == 0x8000);
    CHECK(to_bf16(0.0f) == 0);
    CHECK(to_bf16(-0.0f) == 0x8000);
    // bf16 keeps 8 significant bits: relative rounding error at most 2^-8 for normal numbers.
    std::mt19937 rng(1);
    std::uniform_real_distribution<float> u(-1e3f, 1e3f);
    for (int i = 0; i < 10000; ++i) {
        const float x = u(rng);
        REQUIRE(std::fabs(from_bf16(to_bf16(x)) - x) <= std::ldexp(std::fabs(x), -8));
    }
}

TEST_CASE("bf16 packers match their scalar definitions on ragged shapes, padding zeroed") {
    std::mt19937 rng(7);
    // Random bit patterns as well as ordinary values: the vectorized packers must round
    // every input (NaN, inf, subnormals) exactly like to_bf16.
    auto noisy = [&](std::size_t rows, std::size_t cols) {
        auto m = random_matrix(rows, cols, rng);
        for (std::size_t i = 0; i < m.size(); i += 7) m[i] = from_bits(std::uint32_t(rng()));
        return m;
    };
    struct Shape {
        std::size_t rows, cols;
    };
    for (const Shape s : {Shape{1, 1}, Shape{5, 3}, Shape{16, 16}, Shape{31, 17}, Shape{33, 108},
                          Shape{128, 128}, Shape{100, 5}, Shape{64, 130}}) {
        CAPTURE(s.rows);
        CAPTURE(s.cols);
        const std::size_t lds = s.cols + 3;
        const auto src = noisy(s.rows, lds);
        auto at = [&](std::size_t r, std::size_t c) { return to_bf16(src[r * lds + c]); };
        {  // rows layout
            const std::size_t ldd = round_up(s.cols, 32), rows_pad = round_up(s.rows, 16);
            Bf16Buffer dst(rows_pad * ldd, 0xdead);
            pack_rows(src.data(), s.rows, s.cols, lds, dst.data(), ldd, rows_pad);
            for (std::size_t r = 0; r < rows_pad; ++r)
                for (std::size_t c = 0; c < ldd; ++c)
                    REQUIRE(dst[r * ldd + c] == ((r < s.rows && c < s.cols) ? at(r, c) : 0));
        }
        {  // transposed rows layout (both the vector path's shape and an odd one)
            for (const std::size_t ldd : {round_up(s.rows, 32), s.rows + 1}) {
                const std::size_t cols_pad = round_up(s.cols, 16);
                Bf16Buffer dst(cols_pad * ldd, 0xdead);
                pack_transposed(src.data(), s.rows, s.cols, lds, dst.data(), ldd, cols_pad);
                for (std::size_t c = 0; c < cols_pad; ++c)
                    for (std::size_t r = 0; r < ldd; ++r)
                        REQUIRE(dst[c * ldd + r] == ((r < s.rows && c < s.cols) ? at(r, c) : 0));
            }
        }
        {  // VNNI layout of the rows x cols matrix (K = rows)
            const std::size_t k_pad = round_up(s.rows, 32), ldd = 2 * round_up(s.cols, 16);
            Bf16Buffer dst(k_pad / 2 * ldd, 0xdead);
            pack_vnni(src.data(), s.rows, s.cols, lds, dst.data(), ldd, k_pad);
            for (std::size_t kk = 0; kk < k_pad; ++kk)
                for (std::size_t j = 0; j < ldd / 2; ++j)
                    REQUIRE(dst[(kk / 2) * ldd + 2 * j + kk % 2] ==
                            ((kk < s.rows && j < s.cols) ? at(kk, j) : 0));
        }
    }
}

TEST_CASE("bf16 GEMM (AMX and AVX-512 BF16) matches a double reference on ragged shapes") {
    require_bf16();
    for (const Bf16Backend backend : usable_backends()) {
        CAPTURE(bf16_backend_name(backend));
        std::mt19937 rng(3);
        struct Shape {
            std::size_t m, n, k;
        };
        // The trainer's shapes (v1: forward 128x128x108, weight gradient 112x128x128, output
        // layer 128x16x128, its input gradient 128x128x5), and ragged ones in every dimension.
        for (const Shape s :
             {Shape{128, 128, 108}, Shape{112, 128, 128}, Shape{128, 16, 128}, Shape{128, 112, 5},
              Shape{1, 1, 1}, Shape{5, 16, 32}, Shape{17, 33, 40}, Shape{100, 130, 70}, Shape{33, 17, 96},
              Shape{48, 80, 33}, Shape{15, 47, 200}}) {
            for (const bool accumulate : {false, true}) {
                CAPTURE(s.m);
                CAPTURE(s.n);
                CAPTURE(s.k);
                CAPTURE(accumulate);
                const auto A = random_matrix(s.m, s.k, rng), B = random_matrix(s.k, s.n, rng);
                const std::size_t kp = round_up(s.k, 32);
                // Strides wider than needed, so row addressing is exercised.
                const std::size_t lda = kp + 32, ldb = 2 * round_up(s.n, 16) + 32, ldc = s.n + 5;
                Bf16Buffer a(round_up(s.m, 16) * lda), b(kp / 2 * ldb);
                pack_rows(A.data(), s.m, s.k, s.k, a.data(), lda, round_up(s.m, 16));
                pack_vnni(B.data(), s.k, s.n, s.n, b.data(), ldb, kp);
                // C with extra rows and columns holding a sentinel that must survive.
                const float sentinel = 12345.0f;
                std::vector<float> C((s.m + 3) * ldc, sentinel), C0 = random_matrix(s.m, s.n, rng);
                if (accumulate)
                    for (std::size_t r = 0; r < s.m; ++r)
                        for (std::size_t j = 0; j < s.n; ++j) C[r * ldc + j] = C0[r * s.n + j];
                gemm_bf16_on(backend, s.m, s.n, kp, a.data(), lda, b.data(), ldb, C.data(), ldc, accumulate);
                for (std::size_t r = 0; r < s.m + 3; ++r)
                    for (std::size_t j = 0; j < ldc; ++j) {
                        if (r < s.m && j < s.n) continue;
                        REQUIRE(C[r * ldc + j] == sentinel);
                    }
                for (std::size_t r = 0; r < s.m; ++r)
                    for (std::size_t j = 0; j < s.n; ++j) {
                        // exact: products of the bf16-rounded operands, summed in double.
                        // ideal: the fp32 operands themselves. mag: sum |a||b| for the bounds.
                        double exact = accumulate ? C0[r * s.n + j] : 0.0, ideal = exact,
                               mag = std::fabs(exact);
                        for (std::size_t q = 0; q < s.k; ++q) {
                            const double x = A[r * s.k + q], y = B[q * s.n + j];
                            exact += double(from_bf16(to_bf16(A[r * s.k + q]))) *
                                     from_bf16(to_bf16(B[q * s.n + j]));
                            ideal += x * y;
                            mag += std::fabs(x * y);
                        }
                        const double got = C[r * ldc + j];
                        // fp32 accumulation of exact products: at most k + 1 roundings of 2^-24
                        // relative to the running magnitude.
                        const double acc_tol = double(s.k + 1) * std::ldexp(mag, -24) * 1.01 + 1e-30;
                        // Each operand rounded to bf16 (relative 2^-8): each product is off by
                        // at most 2^-7 + 2^-16 of its magnitude.
                        const double bf16_tol = (std::ldexp(1.0, -7) + std::ldexp(1.0, -16)) * mag + acc_tol;
                        INFO("C[" << r << "][" << j << "] = " << got << ", exact " << exact << ", ideal "
                                  << ideal);
                        REQUIRE(std::fabs(got - exact) <= acc_tol);
                        REQUIRE(std::fabs(got - ideal) <= bf16_tol);
                    }
            }
        }
    }
}

TEST_CASE("AMX GEMM: tiles configured per thread, concurrent threads agree bit for bit") {
    require_amx();
    std::mt19937 rng(5);
    const std::size_t m = 128, n = 128, k = 128;
    const auto A = random_matrix(m, k, rng), B = random_matrix(k, n, rng);
    Bf16Buffer a(m * k), b(k * n);
    pack_rows(A.data(), m, k, k, a.data(), k, m);
    pack_vnni(B.data(), k, n, n, b.data(), 2 * n, k);
    std::vector<float> ref(m * n);
    gemm_bf16(m, n, k, a.data(), k, b.data(), 2 * n, ref.data(), n, false);
    std::vector<std::vector<float>> out(4, std::vector<float>(m * n));
    std::vector<std::thread> pool;
    for (std::size_t t = 0; t < out.size(); ++t)
        pool.emplace_back([&, t] {
            for (int rep = 0; rep < 50; ++rep)
                gemm_bf16(m, n, k, a.data(), k, b.data(), 2 * n, out[t].data(), n, false);
        });
    for (auto& th : pool) th.join();
    for (const auto& o : out) CHECK(o == ref);
}

namespace {

format::ModelDesc mid_desc() {  // v1 widths (108 -> 128 -> 128 -> 5), smaller tables
    format::ModelDesc d;
    d.grid_resolution = 32;
    d.max_points = 18;
    d.level_resolution = {64, 128};
    d.features_per_level = 3;
    d.log2_table_size = 15;
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    return d;
}

double rel_l2(const std::vector<float>& got, const std::vector<float>& ref) {
    double num = 0, den = 0;
    for (std::size_t i = 0; i < ref.size(); ++i) {
        num += (double(got[i]) - ref[i]) * (double(got[i]) - ref[i]);
        den += double(ref[i]) * ref[i];
    }
    return std::sqrt(num / std::max(den, 1e-300));
}

}  // namespace

TEST_CASE("precision selection: automatic and bf16 use bf16 exactly when a backend is available") {
    const format::ModelDesc d = mid_desc();
    SpheresSource src({{{0.0f, 0.0f, 0.0f}, 0.5f}}, d.box_min, d.box_max);
    const auto occ = src.occupancy(d);
    TrainConfig cfg;
    cfg.threads = 1;
    const MlpPrecision expect = bf16_backend() != Bf16Backend::none ? MlpPrecision::bf16 : MlpPrecision::fp32;
    CHECK(Trainer(d, occ, cfg).mlp_precision() == expect);  // default: automatic
    cfg.mlp_precision = MlpPrecision::bf16;
    CHECK(Trainer(d, occ, cfg).mlp_precision() == expect);
    cfg.mlp_precision = MlpPrecision::fp32;
    CHECK(Trainer(d, occ, cfg).mlp_precision() == MlpPrecision::fp32);
}

TEST_CASE("bf16 loss and gradients agree with fp32 on a real batch of a trained model") {
    require_bf16();
    const format::ModelDesc d = mid_desc();
    SpheresSource src(
        {{{-0.35f, 0.1f, 0.0f}, 0.4f}, {{0.4f, -0.2f, 0.1f}, 0.3f}, {{0.1f, 0.55f, -0.3f}, 0.2f}}, d.box_min,
        d.box_max);
    TrainConfig cfg;
    cfg.steps = 150;
    cfg.batch_size = 4096;
    cfg.threads = 2;
    cfg.mlp_precision = MlpPrecision::fp32;
    Trainer ref(d, src.occupancy(d), cfg);
    std::vector<Sample> raw;
    src.generate(21, 60000, raw);
    ref.train(ref.reachable(raw));  // a partly trained model: realistic activations and gradients
    cfg.mlp_precision = MlpPrecision::bf16;
    Trainer amx(d, src.occupancy(d), cfg);
    REQUIRE(amx.mlp_precision() == MlpPrecision::bf16);
    amx.grid() = ref.grid();
    amx.weights() = ref.weights();
    amx.biases() = ref.biases();
    std::vector<Sample> held;
    src.generate(22, 8000, held);
    const auto batch = ref.reachable(held);
    Gradients g32, g16;
    const LossParts l32 = ref.loss_and_gradients(batch, &g32);
    const LossParts l16 = amx.loss_and_gradients(batch, &g16);
    MESSAGE("loss fp32 " << l32.total << " bf16 " << l16.total << " (vis " << l32.visibility << "/"
                         << l16.visibility << ", dist " << l32.distance << "/" << l16.distance << ", normal "
                         << l32.normal << "/" << l16.normal << ")");
    // The hidden layers' inputs are rounded to bf16 (relative 2^-8): the loss moves by
    // ~1e-4 relative (measured 0.171825 vs 0.171850). Gradients move more: the loss
    // gradient depends on residuals much smaller than the outputs, which the rounded forward
    // shifts, and how much depends on how small the residuals of the reference model are
    // (the reference model itself depends on the build's rounding: -march, FMA contraction,
    // Adam's vectorization). Measured relative L2 differences over three reference models:
    // hidden layers and grid 3-11%; the output layer up to 32% (weights). The output layer's
    // bias gradient is not bounded: it is the batch's sum of signed residuals, which largely
    // cancel, so its relative difference ranges from 39% to 100% with the reference model
    // (100% in a -DLSNIF_NATIVE=OFF build at 60aed00) while no bf16 product enters it. The
    // bf16 backward products alone, with an fp32 forward: 0.1-0.5%. A layout error gives
    // differences of order 100% or more, which the bounds (30% hidden, 60% output layer
    // weights) still catch; the products themselves are checked exactly against a reference
    // in the GEMM test above.
    CHECK(std::fabs(l16.total - l32.total) <= 1e-3 * l32.total);
    for (std::size_t k = 0; k < g32.weights.size(); ++k) {
        const double ew = rel_l2(g16.weights[k], g32.weights[k]), eb = rel_l2(g16.biases[k], g32.biases[k]);
        MESSAGE("layer " << k << ": weight gradient rel. L2 error " << ew << ", bias " << eb);
        const bool output_layer = k + 1 == g32.weights.size();
        CHECK(ew <= (output_layer ? 0.6 : 0.3));
        if (!output_layer) CHECK(eb <= 0.3);
    }
    for (std::size_t l = 0; l < g32.grid.size(); ++l) {
        const double e = rel_l2(g16.grid[l], g32.grid[l]);
        MESSAGE("level " << l << ": grid gradient rel. L2 error " << e);
        CHECK(e <= 0.15);
    }
    // predict_raw stays fp32: identical for both trainers.
    CHECK(amx.predict_raw(batch) == ref.predict_raw(batch));
}
