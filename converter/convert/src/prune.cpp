// The prune stage of convert_stages.hpp: hidden neurons that no ray of the training
// distribution switches on are removed after training (docs/model.md "Inactive neurons").
#include "convert_stages.hpp"

#include <lsnif/base/parallel.hpp>
#include <lsnif/format/forward.hpp>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace lsnif::converter::stages {

namespace {

constexpr std::size_t kChunk = 256;  // rays per forward pass, as the reader's intersect

// ORs into `active` (per hidden layer, per neuron) which neurons are positive after the
// ReLU for the rays [begin, end) that reach the network: the reader's walk and encoding,
// then the hidden layers in fp32 (format::hidden_layer_fp32, as mlp_forward's fp32 path).
void mark_active(const format::Runtime& rt, std::span<const samples::Sample> rays, std::size_t begin,
                 std::size_t end, std::vector<std::vector<std::uint8_t>>& active) {
    const format::Geometry& geo = rt.geo;
    const format::Network& net = rt.net;
    const auto grid = rt.grid_views();
    const std::size_t n = end - begin;
    std::vector<format::Ray> batch(n);
    for (std::size_t i = 0; i < n; ++i) batch[i] = rays[begin + i].ray;
    std::vector<format::RayPoints> pts(n);
    std::vector<format::TraceStatus> status(n);
    format::trace_points_batch(geo, rt.occupancy, batch, pts.data(), status.data());
    std::vector<std::uint32_t> which;
    for (std::size_t i = 0; i < n; ++i)
        if (status[i] == format::TraceStatus::ok) which.push_back(std::uint32_t(i));
    if (which.empty()) return;
    const std::size_t m = which.size();
    std::vector<float> input(m * geo.input_width);
    format::encode_batch(geo, grid.data(), pts.data(), which, input.data());
    std::vector<float> layer[2];
    const float* src = input.data();
    std::size_t lda = geo.input_width;
    for (std::size_t k = 0; k + 1 < net.layer_count(); ++k) {
        std::vector<float>& dst = layer[k % 2];
        dst.resize(m * net.out_padded[k]);
        format::hidden_layer_fp32(net, k, src, m, lda, dst.data());
        for (std::size_t r = 0; r < m; ++r)
            for (std::size_t j = 0; j < net.out[k]; ++j)
                if (dst[r * net.out_padded[k] + j] > 0.0f) active[k][j] = 1;
        src = dst.data();
        lda = net.out_padded[k];
    }
}

// Row-major [rows][cols] fp16 matrix with only the rows (or columns) `keep`.
std::vector<std::uint16_t> keep_rows(const std::vector<std::uint16_t>& w, std::size_t cols,
                                     const std::vector<std::uint32_t>& keep) {
    std::vector<std::uint16_t> out;
    out.reserve(keep.size() * cols);
    for (const std::uint32_t r : keep)
        out.insert(out.end(), w.begin() + r * cols, w.begin() + (r + 1) * cols);
    return out;
}
std::vector<std::uint16_t> keep_columns(const std::vector<std::uint16_t>& w, std::size_t cols,
                                        const std::vector<std::uint32_t>& keep) {
    std::vector<std::uint16_t> out;
    const std::size_t rows = cols ? w.size() / cols : 0;
    out.reserve(rows * keep.size());
    for (std::size_t r = 0; r < rows; ++r)
        for (const std::uint32_t c : keep) out.push_back(w[r * cols + c]);
    return out;
}

}  // namespace

std::vector<std::vector<std::uint8_t>> active_neurons(const format::ModelData& model,
                                                      std::span<const samples::Sample> rays,
                                                      std::uint32_t threads) {
    const format::Runtime rt = format::make_runtime(model, format::MlpArithmetic::fp32);
    const std::size_t hidden = rt.net.layer_count() ? rt.net.layer_count() - 1 : 0;
    const std::uint32_t T = base::resolve_threads(threads);
    // One tally per share, ORed at the end: the same result whichever share ran which chunk.
    std::vector<std::vector<std::vector<std::uint8_t>>> shares(T);
    for (auto& s : shares)
        for (std::size_t k = 0; k < hidden; ++k) s.emplace_back(rt.net.out[k], 0);
    base::parallel_chunks(rays.size(), T, kChunk, [&](std::uint32_t t, std::size_t b, std::size_t e) {
        mark_active(rt, rays, b, e, shares[t]);
    });
    std::vector<std::vector<std::uint8_t>> active(hidden);
    for (std::size_t k = 0; k < hidden; ++k) {
        active[k].assign(rt.net.out[k], 0);
        for (const auto& s : shares)
            for (std::size_t j = 0; j < active[k].size(); ++j) active[k][j] |= s[k][j];
    }
    return active;
}

std::vector<std::uint32_t> remove_inactive_neurons(format::ModelData& model,
                                                   const std::vector<std::vector<std::uint8_t>>& active) {
    std::vector<std::uint32_t> removed(model.desc.hidden_width.size(), 0);
    for (std::size_t k = 0; k < removed.size() && k < active.size(); ++k) {
        const std::uint32_t width = model.desc.hidden_width[k];
        if (active[k].size() != width) continue;  // not this model's tally: leave the layer alone
        std::vector<std::uint32_t> keep;
        for (std::uint32_t j = 0; j < width; ++j)
            if (active[k][j]) keep.push_back(j);
        if (keep.empty()) keep.push_back(0);  // a layer keeps one neuron (FORMAT.md: width >= 1)
        if (keep.size() == width) continue;
        const std::uint32_t in = model.desc.layer_shape(std::uint32_t(k)).second;
        model.weights[k] = keep_rows(model.weights[k], in, keep);
        model.biases[k] = keep_rows(model.biases[k], 1, keep);
        // Layer k + 1 still reads `width` inputs until its columns are dropped.
        model.weights[k + 1] = keep_columns(model.weights[k + 1], width, keep);
        model.desc.hidden_width[k] = std::uint32_t(keep.size());
        removed[k] = width - std::uint32_t(keep.size());
    }
    return removed;
}

}  // namespace lsnif::converter::stages
