// The 8-bit hidden layers (lsnif/format/int8.hpp) against their definition, computed here
// independently: per-row and per-column scales, round-to-nearest-even, exact integer sums,
// one fused multiply-add into the bias. Whatever path the machine takes (AVX-512 VNNI or
// scalar), its results must equal the definition bit for bit.
#include <doctest/doctest.h>

#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/int8.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

using namespace lsnif::format;

namespace {

// The definition of quantize_rows for one row: scale = max / range, q = rint(x * range / max)
// clamped, NaN -> 0.
struct RowRef {
    std::vector<std::int32_t> q;
    float scale = 0;
};
RowRef quantize_ref(const float* x, std::size_t cols, bool signed_input) {
    const float range = signed_input ? 127.0f : 255.0f, lo = signed_input ? -127.0f : 0.0f;
    float m = 0;
    for (std::size_t k = 0; k < cols; ++k) {
        const float a = signed_input ? std::fabs(x[k]) : x[k];
        if (a > m) m = a;
    }
    RowRef r;
    const float inverse = m > 0 ? range / m : 0.0f;
    r.scale = m > 0 ? m / range : 0.0f;
    for (std::size_t k = 0; k < cols; ++k) {
        const float t = x[k] * inverse;
        r.q.push_back(t != t ? 0 : std::int32_t(std::nearbyint(std::clamp(t, lo, range))));
    }
    return r;
}

// A layer's quantized weight (k, j) as a signed value, read back from the VNNI4 layout.
std::int32_t weight(const Int8Layer& l, std::size_t k, std::size_t j) {
    const std::uint8_t b = l.b[(k / 4) * 4 * l.out_padded + 4 * j + k % 4];
    return l.signed_input ? std::int32_t(b) - 128 : std::int32_t(std::int8_t(b));
}

// The definition of gemm_int8 on already quantized rows.
std::vector<float> product_ref(const std::vector<RowRef>& rows, const Int8Layer& l,
                               const std::vector<float>& bias, bool relu) {
    std::vector<float> c(rows.size() * l.out_padded);
    for (std::size_t r = 0; r < rows.size(); ++r)
        for (std::size_t j = 0; j < l.out_padded; ++j) {
            std::int64_t sum = 0;
            for (std::size_t k = 0; k < l.in; ++k) sum += std::int64_t(rows[r].q[k]) * weight(l, k, j);
            const float y = std::fma(float(sum), rows[r].scale * l.scale[j], bias[j]);
            c[r * l.out_padded + j] = relu ? (y > 0 ? y : 0.0f) : y;
        }
    return c;
}

struct Case {
    std::size_t m, in, out_padded, tail;  // tail: ZeroColumns' end (0 = no zero columns)
    bool signed_input;
    std::size_t rest_start = 0;  // ZeroColumns' second run (0 = none)
};

std::size_t bit_equal(const std::vector<float>& a, const std::vector<float>& b) {
    std::size_t n = 0;
    for (std::size_t i = 0; i < a.size(); ++i) n += std::memcmp(&a[i], &b[i], sizeof(float)) == 0;
    return n;
}

}  // namespace

TEST_CASE("quantize_rows follows its definition: per-row scales, nearest even, clamping, NaN and zero rows") {
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> u(-3.f, 3.f);
    for (const bool signed_input : {true, false})
        for (const std::size_t cols : {std::size_t(1), std::size_t(16), std::size_t(129), std::size_t(200)}) {
            CAPTURE(signed_input);
            CAPTURE(cols);
            const std::size_t n = 9, lds = cols + 3;
            std::vector<float> x(n * lds);
            for (float& v : x) v = u(rng);
            std::fill(x.begin() + 2 * lds, x.begin() + 2 * lds + cols, 0.0f);  // an all-zero row
            x[3 * lds] = std::numeric_limits<float>::quiet_NaN();              // a NaN input
            x[4 * lds + cols - 1] = 1e30f;                                     // one huge value
            // Halfway cases: with the row's maximum at the range, x * inverse is exact, so
            // k + 0.5 must round to the even neighbour.
            for (std::size_t k = 0; k < cols; ++k) x[5 * lds + k] = float(k % 7) - 2.5f;
            x[5 * lds] = signed_input ? 127.0f : 255.0f;
            Int8Rows rows;
            quantize_rows(x.data(), n, cols, lds, signed_input, rows);
            REQUIRE(rows.cols == cols);
            REQUIRE(rows.ld % 16 == 0);
            for (std::size_t r = 0; r < n; ++r) {
                CAPTURE(r);
                const RowRef want = quantize_ref(&x[r * lds], cols, signed_input);
                CHECK(std::memcmp(&rows.scale[r], &want.scale, sizeof(float)) == 0);
                std::int32_t sum = 0;
                std::size_t same = 0;
                for (std::size_t k = 0; k < cols; ++k) {
                    const std::uint8_t b = rows.q[r * rows.ld + k];
                    same += (signed_input ? std::int32_t(std::int8_t(b)) : std::int32_t(b)) == want.q[k];
                    sum += want.q[k];
                }
                CHECK(same == cols);
                for (std::size_t k = cols; k < rows.ld; ++k) CHECK(rows.q[r * rows.ld + k] == 0);
                CHECK(rows.sum[r] == (signed_input ? sum : 0));
            }
            CHECK(rows.scale[2] == 0.0f);  // the zero row
        }
}

TEST_CASE("make_int8_layer keeps every weight within half a step of its column's scale") {
    std::mt19937 rng(4);
    std::uniform_real_distribution<float> u(-0.5f, 0.5f);
    for (const bool signed_input : {true, false}) {
        const std::size_t in = 37, op = 48;
        std::vector<float> wt(in * op);
        for (float& w : wt) w = u(rng);
        for (std::size_t k = 0; k < in; ++k) wt[k * op + 5] = 0.0f;  // an all-zero column
        const Int8Layer l = make_int8_layer(wt.data(), in, op, signed_input);
        CHECK(l.b.size() == 40 * op);  // K padded to 4
        CHECK(l.scale[5] == 0.0f);
        for (std::size_t j = 0; j < op; ++j)
            for (std::size_t k = 0; k < 40; ++k) {
                const float w = k < in ? wt[k * op + j] : 0.0f;
                CHECK(std::fabs(float(weight(l, k, j)) * l.scale[j] - w) <= 0.5f * l.scale[j] * 1.0001f);
                CHECK(std::abs(weight(l, k, j)) <= 127);
            }
    }
}

TEST_CASE("the int8 product equals its definition bit for bit, skipped zero columns or not") {
    MESSAGE("AVX-512 VNNI on this machine: " << cpu_features().avx512_vnni
                                             << " (without it the scalar path is what is checked)");
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    // The inference shapes (129 inputs: 108 point features, then 21 ray inputs, the last 18
    // the entry offsets; 128 hidden) and ragged ones: K not a multiple of 4, rows not a
    // multiple of the row block, every column count the kernel splits differently (80 and 96
    // in one block, as pruned layers have; 64-column blocks then 16, 32 or 48), zero runs
    // ending inside a quad.
    for (const Case cs :
         {Case{256, 129, 128, 108, true, 111}, Case{256, 129, 128, 108, true}, Case{37, 128, 128, 0, false},
          Case{13, 71, 48, 51, true, 53}, Case{7, 33, 16, 33, true}, Case{11, 64, 144, 0, false},
          Case{6, 5, 80, 0, false}, Case{50, 128, 80, 0, false}, Case{29, 128, 96, 0, false},
          Case{19, 128, 160, 0, false}, Case{23, 40, 176, 0, false}}) {
        CAPTURE(cs.m);
        CAPTURE(cs.in);
        CAPTURE(cs.rest_start);
        CAPTURE(cs.out_padded);
        std::vector<float> x(cs.m * cs.in), wt(cs.in * cs.out_padded), bias(cs.out_padded);
        std::vector<std::uint32_t> lead(cs.m), rest(cs.m);
        for (std::size_t r = 0; r < cs.m; ++r) {
            lead[r] = cs.tail ? std::uint32_t(rng() % (cs.tail + 1)) : 0;
            rest[r] = cs.rest_start ? std::uint32_t(rng() % (cs.in - cs.rest_start + 1)) : 0;
            if (r % 3 == 0 && r > 0) {  // runs of equal leads, as sorted rows have
                lead[r] = lead[r - 1];
                rest[r] = rest[r - 1];
            }
            for (std::size_t k = 0; k < cs.in; ++k) {
                const bool zero = cs.tail && ((k >= lead[r] && k < cs.tail) ||
                                              (cs.rest_start && k >= cs.rest_start + rest[r]));
                const float v = u(rng);
                x[r * cs.in + k] = zero ? 0.0f : cs.signed_input ? v : std::fabs(v);
            }
        }
        for (float& w : wt) w = u(rng);
        for (float& b : bias) b = u(rng);
        const Int8Layer layer = make_int8_layer(wt.data(), cs.in, cs.out_padded, cs.signed_input);
        Int8Rows rows;
        quantize_rows(x.data(), cs.m, cs.in, cs.in, cs.signed_input, rows);
        std::vector<RowRef> ref;
        for (std::size_t r = 0; r < cs.m; ++r)
            ref.push_back(quantize_ref(&x[r * cs.in], cs.in, cs.signed_input));
        const ZeroColumns zeros{lead.data(), cs.tail, cs.rest_start ? rest.data() : nullptr, cs.rest_start};
        for (const bool relu : {true, false}) {
            CAPTURE(relu);
            const std::vector<float> want = product_ref(ref, layer, bias, relu);
            std::vector<float> full(want.size()), skipped(want.size());
            gemm_int8(cs.m, rows, layer, bias.data(), relu, full.data(), cs.out_padded);
            gemm_int8(cs.m, rows, layer, bias.data(), relu, skipped.data(), cs.out_padded,
                      cs.tail ? &zeros : nullptr);
            CHECK(bit_equal(full, want) == want.size());
            CHECK(bit_equal(skipped, want) == want.size());
        }
        // The fused epilogue: the next layer's rows, as quantize_rows makes them from fp32.
        std::vector<float> relu_out(cs.m * cs.out_padded), scratch;
        gemm_int8(cs.m, rows, layer, bias.data(), true, relu_out.data(), cs.out_padded,
                  cs.tail ? &zeros : nullptr);
        Int8Rows want_next, next;
        quantize_rows(relu_out.data(), cs.m, cs.out_padded, cs.out_padded, false, want_next);
        gemm_int8_relu_quantized(cs.m, rows, layer, bias.data(), next, scratch, cs.tail ? &zeros : nullptr);
        REQUIRE(next.ld == want_next.ld);
        CHECK(std::memcmp(next.q.data(), want_next.q.data(), cs.m * next.ld) == 0);
        CHECK(std::memcmp(next.scale.data(), want_next.scale.data(), cs.m * sizeof(float)) == 0);
    }
}

TEST_CASE(
    "the fused quantization gives quantize_rows' bytes when a row's maximum is denormal (inverse scale "
    "overflows to infinity)") {
    // Zero input rows leave each output at its bias: here positive denormals, zeros and
    // negatives, so a row's maximum is ~1e-40, 255 / max overflows and y * inverse is +inf
    // (or NaN for y = 0): the bytes must saturate to 255 and 0 as quantize_rows' clamp does.
    for (const std::size_t out_padded : {std::size_t(64), std::size_t(128)}) {
        CAPTURE(out_padded);
        const std::size_t m = 7, in = 33;
        std::vector<float> x(m * in, 0.0f), wt(in * out_padded), bias(out_padded);
        std::mt19937 rng(9);
        std::uniform_real_distribution<float> u(-1.f, 1.f);
        for (float& w : wt) w = u(rng);
        for (std::size_t j = 0; j < out_padded; ++j)
            bias[j] = j % 3 == 0 ? 1e-40f * float(j % 5 + 1) : j % 3 == 1 ? 0.0f : -float(j);
        const Int8Layer layer = make_int8_layer(wt.data(), in, out_padded, true);
        Int8Rows rows, want_next, next;
        quantize_rows(x.data(), m, in, in, true, rows);
        std::vector<float> relu_out(m * out_padded), scratch;
        gemm_int8(m, rows, layer, bias.data(), true, relu_out.data(), out_padded);
        REQUIRE(std::isinf(255.0f / relu_out[0 * out_padded + 0]));
        quantize_rows(relu_out.data(), m, out_padded, out_padded, false, want_next);
        gemm_int8_relu_quantized(m, rows, layer, bias.data(), next, scratch);
        std::size_t saturated = 0;
        for (std::size_t j = 0; j < out_padded; ++j) saturated += want_next.q[j] == 255;
        CHECK(saturated == (out_padded + 2) / 3);  // every positive denormal column
        CHECK(std::memcmp(next.q.data(), want_next.q.data(), m * next.ld) == 0);
        CHECK(std::memcmp(next.scale.data(), want_next.scale.data(), m * sizeof(float)) == 0);
    }
}

TEST_CASE("the network with rows in vector lanes gives the layer-by-layer results bit for bit") {
    // Shapes: the default model's (143 signed inputs with empty point slots and entry offsets
    // -> 128 -> 98 padded to 112 -> the output layer), a third hidden layer whose input stops
    // short of the previous padding, a single hidden layer, unsigned first inputs; last hidden
    // layers whose final column group holds 2, 6, 9, 13 and 16 live columns (the kernel runs
    // 4, 8, 12 or 16 of them); row counts around the 16-row block. And a network whose blocks
    // take the clamping paths: every fifth input row is denormal (127 / its maximum
    // overflows) and the next one zero, which leaves that row's first-layer outputs at their
    // biases, positive denormals, zeros and negatives (255 / maximum overflows). The later
    // biases are zero there, so the denormal products reach the outputs and a wrong byte
    // changes them.
    struct Net {
        std::vector<std::size_t> widths;  // inputs, hidden outputs (unpadded), the output layer's 16
        std::size_t tail, rest_start;     // ZeroColumns of the input (0 = none)
        bool signed_input;
        bool denormal_rows = false;
    };
    std::mt19937 rng(17);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (const Net& net :
         {Net{{143, 128, 98, 16}, 126, 129, true}, Net{{143, 128, 98, 70, 16}, 126, 129, true},
          Net{{143, 128, 73, 16}, 126, 129, true}, Net{{33, 48, 16}, 20, 0, true},
          Net{{64, 80, 16}, 0, 0, false}, Net{{64, 45, 16}, 0, 0, false},
          Net{{33, 48, 40, 16}, 0, 0, true, true}}) {
        const std::size_t hidden_count = net.widths.size() - 2, in = net.widths[0];
        std::vector<Int8Layer> hidden;
        std::vector<std::vector<float>> bias;
        for (std::size_t k = 0; k < hidden_count; ++k) {
            const std::size_t kin = net.widths[k], op = (net.widths[k + 1] + 15) / 16 * 16;
            std::vector<float> wt(kin * op, 0.0f), b(op, 0.0f);
            for (std::size_t i = 0; i < kin; ++i)
                for (std::size_t j = 0; j < net.widths[k + 1]; ++j) wt[i * op + j] = u(rng);
            for (std::size_t j = 0; j < net.widths[k + 1]; ++j)
                b[j] = !net.denormal_rows ? 0.2f * u(rng)
                       : k > 0            ? 0.0f
                       : j % 3 == 0       ? 1e-40f * float(j % 5 + 1)
                       : j % 3 == 1       ? 0.0f
                                          : -float(j);
            hidden.push_back(make_int8_layer(wt.data(), kin, op, k == 0 && net.signed_input));
            bias.push_back(b);
        }
        const std::size_t out_in = net.widths[hidden_count];
        std::vector<float> out_wt(out_in * 16), out_bias(16);
        for (float& w : out_wt) w = u(rng);
        for (float& b : out_bias) b = net.denormal_rows ? 0.0f : u(rng);
        for (const std::size_t m : {std::size_t(1), std::size_t(16), std::size_t(37), std::size_t(256)}) {
            CAPTURE(in);
            CAPTURE(hidden_count);
            CAPTURE(m);
            std::vector<float> x(m * in);
            std::vector<std::uint32_t> lead(m), rest(m);
            for (std::size_t r = 0; r < m; ++r) {
                // Sorted by decreasing lead, as the reader's rows are.
                lead[r] = net.tail ? std::uint32_t(net.tail - (r * net.tail) / m) : 0;
                rest[r] = net.rest_start ? std::uint32_t(rng() % (in - net.rest_start + 1)) : 0;
                for (std::size_t k = 0; k < in; ++k) {
                    const bool zero = net.tail && ((k >= lead[r] && k < net.tail) ||
                                                   (net.rest_start && k >= net.rest_start + rest[r]));
                    const float v = u(rng);
                    // Unsigned inputs: a few negatives, which quantization clamps to 0.
                    x[r * in + k] = zero || (net.denormal_rows && r % 5 == 1) ? 0.0f
                                    : net.denormal_rows && r % 5 == 0         ? 1e-40f * v
                                    : net.signed_input || k % 7 == 0          ? v
                                                                              : std::fabs(v);
                }
            }
            const ZeroColumns zeros{lead.data(), net.tail, net.rest_start ? rest.data() : nullptr,
                                    net.rest_start};
            const ZeroColumns* z = net.tail ? &zeros : nullptr;
            Int8Rows rows[2];
            quantize_rows(x.data(), m, in, in, net.signed_input, rows[0]);
            // The layer-by-layer path.
            std::vector<float> last(m * hidden.back().out_padded), scratch;
            for (std::size_t k = 0; k + 1 < hidden_count; ++k)
                gemm_int8_relu_quantized(m, rows[k % 2], hidden[k], bias[k].data(), rows[(k + 1) % 2],
                                         scratch, k == 0 ? z : nullptr);
            gemm_int8(m, rows[(hidden_count - 1) % 2], hidden.back(), bias.back().data(), true, last.data(),
                      hidden.back().out_padded, hidden_count == 1 ? z : nullptr);
            for (const std::size_t outs : {std::size_t(1), std::size_t(5), std::size_t(8)}) {
                CAPTURE(outs);
                std::vector<float> want(m * 16), got(m * 16, -1.0f);
                dense_output_layer(last.data(), m, out_in, hidden.back().out_padded, out_wt.data(),
                                   out_bias.data(), 16, outs, want.data());
                const bool ran =
                    mlp_int8_in_lanes(m, x.data(), in, hidden.data(), bias.data(), hidden_count,
                                      {out_wt.data(), out_bias.data(), out_in, outs}, z, got.data());
                REQUIRE(ran == cpu_features().avx512_vnni);
                if (!ran) continue;
                std::size_t equal = 0, zero_padding = 0;
                for (std::size_t r = 0; r < m; ++r)
                    for (std::size_t o = 0; o < 16; ++o) {
                        if (o < outs)
                            equal += std::memcmp(&got[r * 16 + o], &want[r * 16 + o], sizeof(float)) == 0;
                        else
                            zero_padding += got[r * 16 + o] == 0.0f;
                    }
                CHECK(equal == m * outs);
                CHECK(zero_padding == m * (16 - outs));
            }
        }
    }
}
