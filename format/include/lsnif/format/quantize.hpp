// 8-bit affine quantization of hash-grid features (FORMAT.md §6.4.1, grid_encoding 1).
//
// The format fixes only the dequantization: byte q of level l stands for
//     v = fmaf(q, scale_l, offset_l)
// i.e. q * scale_l + offset_l computed exactly and rounded once to the nearest binary32
// (ties to even). A fused multiply-add is exact to specify and does not depend on the
// compiler's contraction settings or on the SIMD width, so every reader, scalar or
// vector, CPU or GPU, gets the same floats. How a writer picks (scale, offset, q) is its
// own business; quantize_level below is the reference writer's choice.
#pragma once

#include <lsnif/format/container.hpp>

#include <cmath>
#include <cstdint>
#include <span>
#include <vector>

namespace lsnif::format {

// The normative dequantization (FORMAT.md §6.4.1). std::fma on floats is fmaf: a single
// instruction where the target has FMA, libm's correctly rounded fmaf otherwise.
inline float dequantize_u8(std::uint8_t q, float scale, float offset) {
    return std::fma(float(q), scale, offset);
}

// One quantized level: values.size() bytes and its dequantization pair.
struct QuantizedLevel {
    LevelAffine affine;
    std::vector<std::uint8_t> q;
};

// Quantizes one level's feature values (any length, all finite; units are whatever the
// features are). offset = min(values); scale = (max - min) / 255 rounded to f32 (0 when
// all values are equal: a constant level), lowered by ulps in the rare case where
// dequantizing 255 would overflow. Each q is then the byte whose dequantized value is
// nearest to the input (ties: the smaller q), so |dequantize_u8(q) - v| <= scale / 2 up to
// the f32 roundings of scale and of the fma. Returns LSNIF_ERR_NONFINITE for a NaN or
// infinite input, LSNIF_ERR_OUT_OF_MEMORY if allocation fails; never throws.
Result<QuantizedLevel> quantize_level(std::span<const float> values);
// Same for binary16 bit patterns (converted exactly to f32 first).
Result<QuantizedLevel> quantize_level_fp16(std::span<const std::uint16_t> halves);

// An fp16 model turned into the same model with a u8_affine grid (every level quantized
// with quantize_level_fp16; everything else copied). The input must pass validate_model
// and have an fp16 grid (LSNIF_ERR_INVALID_ARGUMENT otherwise).
Result<ModelData> quantize_model(const ModelData& fp16_model);

// Level `level` of a u8_affine model dequantized to f32 by the normative formula, in the
// layout of ModelData::grid_u8 (entries * F); empty if the model has no such level.
// For tools and tests.
std::vector<float> dequantize_level(const ModelData& model, std::uint32_t level);

}  // namespace lsnif::format
