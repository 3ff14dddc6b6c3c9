// 8-bit operands for the reader's hidden layers (MlpArithmetic::int8): each row of a layer's
// input quantized with its own scale, each weight column with its own, products summed
// exactly in int32 by AVX-512 VNNI (VPDPBUSD: 64 byte products per instruction, twice
// VDPBF16PS's 32 at the same issue rate) and rescaled to fp32 with the bias. Used by
// forward.cpp's mlp_forward; internal C++ API, like forward.hpp.
//
// The arithmetic (symmetric linear quantization, the scheme of Jacob et al., "Quantization
// and Training of Neural Networks for Efficient Integer-Arithmetic-Only Inference", CVPR
// 2018, with per-row activation and per-column weight scales instead of per-tensor ones):
//   x[r][k] ~ sx[r] * qx[r][k],   w[k][n] ~ sw[n] * qw[k][n],
//   y[r][n] = sx[r] * sw[n] * sum_k qx[r][k] * qw[k][n] + bias[n].
// VPDPBUSD multiplies unsigned by signed bytes, so one operand must be unsigned:
//  * unsigned inputs (a ReLU's output, >= 0): qx in [0, 255], sx = max_k x / 255; qw signed
//    in [-127, 127].
//  * signed inputs (the encoded features of the first layer): qx in [-127, 127],
//    sx = max_k |x| / 127; the weights are stored offset, qw + 128 in [1, 255], and the
//    kernel subtracts 128 * sum_k qx[r][k] (Int8Rows::sum) from each row's sum. A zero input
//    has qx = 0 and adds nothing to either sum, so ZeroColumns stay skippable.
// Integer sums are exact (|sum| <= K * 255 * 128, within int32 for K <= kInt8MaxInputs) and
// the int32 -> fp32 conversion rounds the same way on both paths (exactly, for K <= 518,
// e.g. the default model's 129 inputs): the AVX-512 kernel and the scalar path give
// bit-identical results for finite inputs, with or without skipped columns.
//
// Layouts (bytes):
//  * A, "rows": qx[r][k] at q[r * ld + k], ld = round_up(cols, 16), zero padded.
//  * B, "VNNI4": four consecutive K rows interleaved, element (k, n) at
//    b[(k / 4) * 4 * np + 4 * n + k % 4], K padded to 4 and N to np (a multiple of 16) with
//    the stored form of 0 (128 for signed inputs). Each 32-bit element of a B row holds
//    four K values of one column: what VPDPBUSD reads against a broadcast dword of A.
#pragma once

#include <lsnif/format/bf16.hpp>

#include <cstddef>
#include <cstdint>
#include <vector>

namespace lsnif::format {

// The widest layer input the int8 path takes (set_mlp_arithmetic falls back beyond it).
inline constexpr std::size_t kInt8MaxInputs = 16384;

// One hidden layer's weights for gemm_int8.
struct Int8Layer {
    std::size_t in = 0;           // K: inputs
    std::size_t out_padded = 0;   // N: outputs, a multiple of 16
    bool signed_input = false;    // the layer's inputs may be negative (see above)
    std::vector<std::uint8_t> b;  // VNNI4 layout, round_up(in, 4) / 4 rows of 4 * out_padded bytes
    std::vector<float> scale;     // sw[n], out_padded values (0 for all-zero columns)
    // signed_input only, for mlp_int8_in_lanes: the weights as two's complement bytes in the
    // VNNI4 layout, and per column n the sum of its quantized weights over quads [0, p) at
    // quad_prefix[p * out_padded + n], p in [0, quads].
    std::vector<std::uint8_t> w_signed;
    std::vector<std::int32_t> quad_prefix;
};

// Quantizes W^T (`wt`: in x out_padded, row-major fp32, the Network layout). Non-finite
// weights make their column's results non-finite, as in fp32; never undefined behaviour.
Int8Layer make_int8_layer(const float* wt, std::size_t in, std::size_t out_padded, bool signed_input);

// A layer's input quantized row by row (A operand).
struct Int8Rows {
    std::size_t cols = 0, ld = 0;
    std::vector<std::uint8_t> q;    // rows layout
    std::vector<float> scale;       // sx[r]
    std::vector<std::int32_t> sum;  // sum_k qx[r][k] (signed inputs; 0 otherwise)
};

// Quantizes rows [0, n) of `src` (cols values each, row stride lds) into `out`, growing its
// buffers as needed. signed_input as in Int8Layer: unsigned rows clamp negatives to 0. A
// row of zeros gets scale 0 and all-zero q. NaN inputs become 0 (their row's scale may then
// be NaN or infinite: the results are garbage, as in fp32, but defined).
void quantize_rows(const float* src, std::size_t n, std::size_t cols, std::size_t lds, bool signed_input,
                   Int8Rows& out);

// C[r][j] = epilogue(sx[r] * sw[j] * sum_k qx[r][k] qw[k][j] + bias[j]) for r < m, j < n =
// layer.out_padded, with `relu` applying max(x, 0) (+0 for x <= 0). Contract: `a` holds m
// quantized rows of a.cols == layer.in inputs with layer.signed_input's convention; `bias`
// has out_padded values; `zeros`, if given, true of the unquantized input (zero inputs
// quantize to 0). Only the m x n region of C is written. Thread-safe.
void gemm_int8(std::size_t m, const Int8Rows& a, const Int8Layer& layer, const float* bias, bool relu,
               float* c, std::size_t ldc, const ZeroColumns* zeros = nullptr);

// The widest layer gemm_int8_relu_quantized quantizes in its kernel's epilogue (wider ones
// go through fp32 rows and quantize_rows: the same bytes, slower).
inline constexpr std::size_t kInt8FusedWidth = 128;

// The same products with relu = true, the result quantized for the next layer as
// quantize_rows(C, m, layer.out_padded, ..., signed_input = false, next) would, without
// writing C (`scratch` holds it only on the paths that need it). Bit-identical to that pair
// of calls for finite inputs.
void gemm_int8_relu_quantized(std::size_t m, const Int8Rows& a, const Int8Layer& layer, const float* bias,
                              Int8Rows& next, std::vector<float>& scratch,
                              const ZeroColumns* zeros = nullptr);

// The fp32 output layer after the int8 hidden layers, for mlp_int8_in_lanes: W^T (`in` x
// 16, the Network layout for 16 padded outputs), its 16 biases, and how many leading
// outputs the caller reads.
struct Int8OutputLayer {
    const float* wt;
    const float* bias;
    std::size_t in, outs;
};

// A whole network, `hidden_count` int8 hidden layers (ReLU) then the fp32 output layer, 16
// rows at a time with the rows in vector lanes: the input quantized per row straight into
// lanes, then each VPDPBUSD takes four inputs of 16 rows against a broadcast dword of one
// column's weights, so a layer's epilogue (rescale, the rows' maxima, the next layer's scales
// and bytes) runs on 16 rows per instruction with no horizontal reduction or scalar
// division. Reads x[r][0..hidden[0].in) (row stride lda) for r < m; writes C[r][0..16) for
// r < m (columns from `outs` on are 0), bit for bit what the layer-by-layer path gives in
// the first `outs` columns: quantize_rows, gemm_int8_relu_quantized for each hidden layer
// but the last, gemm_int8 with ReLU for the last, dense_output_layer (finite inputs;
// integer sums are exact in any order). Contract: hidden[k].in equals the previous layer's
// out_padded or fewer; `zeros` as in gemm_int8, true of x. Returns false and writes nothing
// where it does not apply (no AVX-512 VNNI, hidden_count 0, out.outs outside
// {1, 5, 6, 7, 8}); the caller then takes the layer-by-layer path.
bool mlp_int8_in_lanes(std::size_t m, const float* x, std::size_t lda, const Int8Layer* hidden,
                       const std::vector<float>* hidden_bias, std::size_t hidden_count,
                       const Int8OutputLayer& out, const ZeroColumns* zeros, float* c);

}  // namespace lsnif::format
