// Reference writer-side quantization of FORMAT.md §6.4.1; see quantize.hpp for contracts.
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>

#include <algorithm>
#include <new>

namespace lsnif::format {

Result<QuantizedLevel> quantize_level(std::span<const float> values) {
    try {
        QuantizedLevel out;
        if (values.empty()) return out;
        float lo = values[0], hi = values[0];
        for (float v : values) {
            if (!std::isfinite(v))
                return Error{LSNIF_ERR_NONFINITE, UINT64_MAX, "cannot quantize a NaN or infinite feature"};
            lo = std::min(lo, v);
            hi = std::max(hi, v);
        }
        // The range in double: hi - lo may exceed FLT_MAX, its 1/255 never does.
        float scale = hi > lo ? float((double(hi) - double(lo)) / 255.0) : 0.0f;
        // Rounding scale up can push q = 255 past FLT_MAX when hi is near it; a reader
        // rejects such a level (NONFINITE), so give up the last ulps of range instead.
        while (!std::isfinite(dequantize_u8(255, scale, lo))) scale = std::nextafter(scale, 0.0f);
        out.affine = {scale, lo};
        out.q.resize(values.size());
        for (std::size_t i = 0; i < values.size(); ++i) {
            const double v = values[i];
            int q = 0;
            if (scale > 0.0f) q = int(std::clamp(std::nearbyint((v - lo) / scale), 0.0, 255.0));
            // The estimate can be one step off the byte whose fma result is nearest, since
            // the reader rounds q * scale + offset to f32: check the neighbours.
            int best = q;
            double best_err = std::fabs(double(dequantize_u8(std::uint8_t(q), scale, lo)) - v);
            for (int c : {q - 1, q + 1}) {
                if (c < 0 || c > 255) continue;
                const double err = std::fabs(double(dequantize_u8(std::uint8_t(c), scale, lo)) - v);
                if (err < best_err || (err == best_err && c < best)) best = c, best_err = err;
            }
            out.q[i] = std::uint8_t(best);
        }
        return out;
    } catch (const std::bad_alloc&) {
        return Error{LSNIF_ERR_OUT_OF_MEMORY, UINT64_MAX, "out of memory"};
    }
}

Result<QuantizedLevel> quantize_level_fp16(std::span<const std::uint16_t> halves) {
    try {
        return quantize_level(halves_to_floats(halves));
    } catch (const std::bad_alloc&) {
        return Error{LSNIF_ERR_OUT_OF_MEMORY, UINT64_MAX, "out of memory"};
    }
}

Result<ModelData> quantize_model(const ModelData& in) {
    if (in.desc.grid_encoding != GridEncoding::fp16)
        return Error{LSNIF_ERR_INVALID_ARGUMENT, UINT64_MAX,
                     "quantize_model needs a model with an fp16 grid"};
    if (Error e = validate_model(in)) return e;
    try {
        ModelData out = in;
        out.desc.grid_encoding = GridEncoding::u8_affine;
        out.grid.clear();
        out.version_minor = out.desc.minor_version();
        for (const auto& level : in.grid) {
            auto q = quantize_level_fp16(level);
            if (!q) return q.error();
            out.grid_affine.push_back(q->affine);
            out.grid_u8.push_back(std::move(q->q));
        }
        return out;
    } catch (const std::bad_alloc&) {
        return Error{LSNIF_ERR_OUT_OF_MEMORY, UINT64_MAX, "out of memory"};
    }
}

std::vector<float> dequantize_level(const ModelData& m, std::uint32_t level) {
    if (level >= m.grid_u8.size() || level >= m.grid_affine.size()) return {};
    const auto& q = m.grid_u8[level];
    const LevelAffine a = m.grid_affine[level];
    std::vector<float> out(q.size());
    for (std::size_t i = 0; i < q.size(); ++i) out[i] = dequantize_u8(q[i], a.scale, a.offset);
    return out;
}

}  // namespace lsnif::format
