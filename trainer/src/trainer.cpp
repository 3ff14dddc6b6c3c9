// Training loop; see trainer.hpp for the contracts.
#include <lsnif/format/half.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <lsnif/base/clock.hpp>
#include <lsnif/base/math.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include "amx.hpp"
#include "kernels.hpp"

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>

namespace lsnif::trainer {

using format::Geometry;
using format::OutputLayout;
using format::RayPoints;
using format::TraceStatus;

MlpPrecision resolve_precision(MlpPrecision requested) {
    return requested != MlpPrecision::fp32 && detail::bf16_backend() != detail::Bf16Backend::none
               ? MlpPrecision::bf16
               : MlpPrecision::fp32;
}

namespace {

// adam_update_rows' element pass over n elements: step[i] is the element's step size and
// on[i] is 1 for an element of an active row (0: keep its state). Restrict-qualified
// parameters: without them the six-way alias check exceeds what the vectorizer will version
// for, and the loop stayed scalar.
// Returns the largest |p| as its bit pattern (order-preserving for |p|, and a NaN comes out
// largest): an integer max reduction vectorizes, a float one does not. Not inlined: the
// caller's pointers would lose their restrict qualification.
[[gnu::noinline]] std::uint32_t adam_elements(float* __restrict p, float* __restrict m, float* __restrict v,
                                              float* __restrict g, const float* __restrict step,
                                              const float* __restrict on, std::size_t n, float grad_scale,
                                              const AdamConfig c) {
    std::uint32_t pmax = 0;
    for (std::size_t i = 0; i < n; ++i) {
        const AdamState s = adam_step(p[i], m[i], v[i], g[i], step[i], grad_scale, c);
        const bool keep = on[i] == 0.0f;
        m[i] = keep ? m[i] : s.m;
        v[i] = keep ? v[i] : s.v;
        const float pi = keep ? p[i] : s.p;
        p[i] = pi;
        g[i] = keep ? g[i] : 0.0f;
        pmax = std::max(pmax, std::bit_cast<std::uint32_t>(pi) & 0x7fffffffu);
    }
    return pmax;
}

}  // namespace

float adam_update_rows(const SparseRows& r, std::size_t rb, std::size_t re, float lr,
                       const double* correction, float grad_scale, const AdamConfig& c) {
    constexpr std::size_t kRows = 32;
    const std::uint32_t F = r.F;
    thread_local std::vector<float> step, on;  // per element: step size, 1 if the row is active
    step.resize(kRows * F);
    on.resize(kRows * F);
    float* const st = step.data();  // the thread_local lookups once, not per row
    float* const onp = on.data();
    std::uint32_t pmax = 0;
    for (std::size_t r0 = rb; r0 < re; r0 += kRows) {
        const std::size_t r1 = std::min(re, r0 + kRows);
        for (std::size_t row = r0; row < r1; ++row) {
            // Branch-free: most rows are active, but which ones is data-dependent.
            const bool is_active = r.active[row] != 0;
            const std::uint32_t t = r.row_step[row] + std::uint32_t(is_active);
            r.row_step[row] = t;
            r.active[row] = 0;
            const float s = is_active ? float(double(lr) * correction[t]) : 0.0f;
            const float a = is_active ? 1.0f : 0.0f;
            for (std::uint32_t f = 0; f < F; ++f) st[(row - r0) * F + f] = s, onp[(row - r0) * F + f] = a;
        }
        const std::size_t base = r0 * F;
        pmax = std::max(pmax, adam_elements(r.p + base, r.m + base, r.v + base, r.g + base, st, onp,
                                            (r1 - r0) * F, grad_scale, c));
    }
    return std::bit_cast<float>(pmax);
}

std::string mlp_arithmetic(MlpPrecision requested) {
    if (resolve_precision(requested) == MlpPrecision::fp32) return "fp32";
    return std::string("bf16/") + detail::bf16_backend_name(detail::bf16_backend());
}

const char* precision_name(MlpPrecision p) {
    switch (p) {
        case MlpPrecision::fp32: return "fp32";
        case MlpPrecision::bf16: return "bf16";
        case MlpPrecision::automatic: return "automatic";
    }
    return "?";
}

namespace {

constexpr std::size_t kSub = 128;  // rows per sub-chunk: keeps activations in L2
// A batch is cut into chunks of whole sub-chunks that depend on the batch size alone (never
// on the thread count): each chunk's gradients are summed over its rows in order, and the
// chunks are then added in chunk order, so a step gives the same bits on any number of
// threads (threads only decide who computes which chunk). At most kMaxChunks per batch keeps
// the per-chunk gradient buffers (~150 KB each at the default width) and their reduction
// small; at least 2 sub-chunks per chunk keeps three threads busy on a 2048-row batch.
constexpr std::size_t kMaxChunks = 32;
// Grid rows per block of the gradient norm: the norm of the hash-grid gradient is summed per
// block of this many rows, then over blocks in order, and threads own whole blocks.
constexpr std::size_t kNormBlock = 1024;
constexpr float kMaxParam = 1e4f;  // larger magnitudes are treated as divergence (fp16 max 65504)

std::uint32_t pad16(std::uint32_t n) {
    return (n + 15u) & ~15u;
}
std::uint32_t pad32(std::uint32_t n) {
    return (n + 31u) & ~31u;
}  // K of a bf16 product

using Rng = base::SplitMix64;

// Runs fn(t) for t in [0, T) on the shared pool (the caller is thread 0).
template <class F>
void parallel(std::uint32_t T, F&& fn) {
    base::run_on_threads(T, fn);
}

// The logistic function in the stable form for either sign, in double with base::exp (the
// same bits on every machine), rounded once to float.
float sigmoid(float z) {
    const double e = base::exp(-std::fabs(double(z)));
    return float(z >= 0 ? 1.0 / (1.0 + e) : e / (1.0 + e));
}

// Rows of each chunk of a batch of `batch` rows (see kMaxChunks).
std::size_t chunk_rows(std::size_t batch) {
    const std::size_t per = (batch + kMaxChunks - 1) / kMaxChunks;
    return std::max(2 * kSub, (per + kSub - 1) / kSub * kSub);
}

// Per-thread scratch of one sub-chunk's forward and backward pass. Aligned so that two
// threads' buffer headers never share a cache line.
struct alignas(128) Work {
    std::vector<RayPoints> pts;
    std::vector<float> x;                 // kSub x in0
    std::vector<std::vector<float>> act;  // per layer output, kSub x outp
    std::vector<float> d0, d1;            // gradient ping-pong, kSub x max padded width
    // The first layer's zero inputs in the sub-chunk (empty_inputs): per row, the end of its
    // points' features and its count of entry offsets; per input column, the rows that may
    // hold a nonzero value (a prefix: rows come in decreasing point count).
    std::vector<std::uint32_t> lead, rest, live_rows;
    format::ZeroColumns zeros{nullptr, 0};
    std::vector<std::uint32_t> order;  // the chunk's batch rows in decreasing point count
    // bf16 path only (empty in fp32): operands of the bf16 products of one sub-chunk.
    detail::Bf16Buffer a_rows;  // forward A: layer input, kSub x pad32(in)
    detail::Bf16Buffer a_t;     // weight-gradient A: layer input transposed, pad16(in) x pad32(kSub)
    detail::Bf16Buffer g_rows;  // input-gradient A: G, kSub x pad32(out)
    detail::Bf16Buffer g_vnni;  // weight-gradient B: G in pair-of-rows layout, pad32(kSub)/2 x 2 outp
};

// What one chunk of a batch contributes to a step, summed over the chunk's rows in order and
// kept apart until the step adds the chunks in chunk order.
struct alignas(128) ChunkResult {
    std::vector<std::vector<float>>
        dwt;  // per layer, pad16(in) x outp (transposed layout); zero between steps
    std::vector<std::vector<float>> db;  // per layer, outp; zero between steps
    // The chunk's samples, in batch order, for the grid-gradient scatter: per sample its
    // `count` points' grid coordinates (count x 3), then the gradients of their features
    // (count x L x F); and the counts.
    std::vector<float> point_grads;
    std::vector<std::uint16_t> point_counts;
    LossParts loss;
};

// Relative cost of one level's pass in scatter_grid_gradients: every sample's corners are
// computed and the live ones added. Faces of an aligned level lie on lattice planes (4
// corners for most points, 8 otherwise), and a table larger than 1 MiB (a core's L2 on the
// reference machines) makes the additions miss cache. A relative weight, not a time: it only
// orders levels for owned_rows (per-level pass times: docs/investigations/grid-and-levels.md).
double scatter_cost(const format::ModelDesc& desc, const Geometry& geo, std::uint32_t level) {
    const std::uint64_t table_bytes = desc.level_entries(level) * desc.features_per_level * sizeof(float);
    return (geo.levels[level].aligned ? 2.0 : 3.0) + (table_bytes > (std::uint64_t{1} << 20) ? 1.0 : 0.0);
}

// The share of grid rows each of T threads owns (Impl::owned): [first, last) per level.
// A thread that owns rows of a level passes over every sample's corners on that level, so
// with at least as many levels as threads each thread owns whole levels, dealt costliest
// first to the thread with the least estimated work (scatter_cost); otherwise every
// level's rows are split evenly. Which thread adds a row's gradients does not change them
// (each row adds its samples in batch order), so the assignment never changes the weights.
std::vector<std::vector<std::pair<std::size_t, std::size_t>>> owned_rows(const format::ModelDesc& desc,
                                                                         const Geometry& geo,
                                                                         std::uint32_t T) {
    const std::uint32_t L = desc.level_count();
    std::vector<std::vector<std::pair<std::size_t, std::size_t>>> owned(
        T, std::vector<std::pair<std::size_t, std::size_t>>(L, {0, 0}));
    if (L >= T) {
        std::vector<double> cost(L);
        std::vector<std::uint32_t> order(L);
        for (std::uint32_t l = 0; l < L; ++l) {
            cost[l] = scatter_cost(desc, geo, l);
            order[l] = l;
        }
        std::stable_sort(order.begin(), order.end(),
                         [&](std::uint32_t a, std::uint32_t b) { return cost[a] > cost[b]; });
        std::vector<double> load(T, 0.0);
        for (const std::uint32_t l : order) {
            const auto t = std::uint32_t(std::min_element(load.begin(), load.end()) - load.begin());
            owned[t][l] = {0, desc.level_entries(l)};
            load[t] += cost[l];
        }
        return owned;
    }
    for (std::uint32_t l = 0; l < L; ++l) {
        // Whole blocks of the gradient norm (kNormBlock), so a block has one owner.
        const std::size_t n = desc.level_entries(l),
                          per = ((n + T - 1) / T + kNormBlock - 1) / kNormBlock * kNormBlock;
        for (std::uint32_t t = 0; t < T; ++t)
            owned[t][l] = {std::min(n, t * per), std::min(n, (t + 1) * per)};
    }
    return owned;
}

}  // namespace

struct Trainer::Impl {
    std::vector<Work> work;                // per thread
    std::vector<ChunkResult> chunks;       // per chunk of the current batch (grown on demand)
    format::Network net;                   // forward layout of the current master weights
    std::vector<std::vector<float>> wpad;  // per layer [out][pad16(in)] for dX = G W
    std::vector<float> zeros;              // bias for the backward products
    // bf16 path: the current weights as B operands, refreshed every step (they change).
    std::vector<detail::Bf16Buffer> wf;  // per layer, forward: Wt (K = in) in VNNI layout
    std::vector<detail::Bf16Buffer> wb;  // per layer, input gradient: W (K = out) in VNNI layout
    // Adam state.
    std::vector<std::vector<float>> gm, gv, wm, wv, bm, bv;
    std::vector<std::vector<std::uint32_t>> row_step;
    std::vector<double> grid_correction;  // [t] = adam_bias_correction(grid_adam, t); [0] unused
    // The grid gradient of the step, per level (entries x F). Rows without gradient are
    // zero between steps: the scatter adds into them, Adam and clear_grid_gradients zero them.
    std::vector<std::vector<float>> gsum;
    // Per level and block of kNormBlock rows: the sum of squares of the block's rows of gsum.
    std::vector<std::vector<double>> gsum_norm2;
    // Rows thread t owns, per level: [first, last). The levels' rows laid end to end are cut
    // into one contiguous share per thread, so every row has one writer (no per-thread
    // tables to reduce); with two threads and two levels of equal size, one level each.
    std::vector<std::vector<std::pair<std::size_t, std::size_t>>> owned;
    std::vector<std::vector<std::uint8_t>> active;
    std::vector<std::vector<float>> wgrad, bgrad;  // reduced MLP gradient, file layout
    double ema = 0;
    // prepare_append()'s per-sample scratch, kept across rounds (see PreparedSet).
    struct PrepareScratch {
        Buffer<std::uint8_t> ok;
        Buffer<std::uint16_t> count;
        Buffer<float> tn, tf, t0, g;
    } prep;
    struct Snapshot {
        std::vector<std::vector<float>> grid, w, b, gm, gv, wm, wv, bm, bv;
        std::vector<std::vector<std::uint32_t>> row_step;
        std::uint64_t step = 0;
        double ema = 0;
        bool valid = false;
    } snap;

    // The stages of Trainer::loss_and_gradients, in order. Each needs `net` made from the
    // current master weights.
    // Lays the current weights out as the backward products want them: VNNI-packed bf16
    // operands (wf, wb) or zero-padded fp32 rows (wpad).
    void stage_weights(const format::ModelDesc& desc, const std::vector<std::vector<float>>& w, bool bf16);
    // Backpropagates dL/d(output) (in w.d0) through the layers of one sub-chunk of n rows,
    // accumulating the chunk's c.dwt and c.db; returns dL/d(input features), n rows of
    // pad16(input_width) (one of w.d0/w.d1).
    // `ld` receives the returned rows' stride: for fp32, only the point features of the
    // sub-chunk's fullest row are computed (what the scatter reads).
    float* mlp_backward(const Geometry& geo, std::size_t n, bool bf16, Work& w, ChunkResult& c,
                        std::size_t& ld) const;
    // Makes `count` chunk results available, with zeroed gradients.
    void prepare_chunks(const format::ModelDesc& desc, std::size_t count);
    // Sums the first `count` chunks' MLP gradients, in chunk order, into wgrad/bgrad (file
    // layout) and zeroes theirs; the elements are split among `threads` threads.
    void reduce_mlp_gradients(const format::ModelDesc& desc, std::size_t count, std::uint32_t threads);
    // Adds every sample's share of dL/d(features) (the first `count` chunks' point_grads)
    // into gsum and marks the rows in `active`; thread t writes only the rows it owns,
    // visiting the samples in batch order, so each row's sum has the same order for any
    // thread count. Thread t then sums the squares of its blocks of rows into gsum_norm2.
    void scatter_grid_gradients(const Geometry& geo, std::size_t count);
    // The sum of squares of gsum: gsum_norm2 added over levels and blocks in order.
    double grid_norm2() const;
    // Zeroes gsum's active rows and clears `active` (a step that is not applied).
    void clear_grid_gradients(std::uint32_t F);
    // Copies the reduced gradients out (gradient checks), then clear_grid_gradients.
    void export_gradients(std::uint32_t F, Gradients& grads);
};

Trainer::Trainer(const format::ModelDesc& desc, std::vector<std::uint8_t> occupancy, const TrainConfig& cfg)
    : impl_(new Impl),
      desc_(desc),
      geo_(format::make_geometry(desc)),
      occupancy_(std::move(occupancy)),
      cfg_(cfg) {
    threads_ = base::resolve_threads(cfg.threads);
    precision_ = resolve_precision(cfg.mlp_precision);
    Rng rng{cfg.seed * 0x2545F4914F6CDD1Dull + 1};
    for (std::uint32_t l = 0; l < desc.level_count(); ++l) {
        grid_.emplace_back(desc.level_entries(l) * desc.features_per_level);
        for (float& x : grid_.back()) x = rng.uniform(-1e-4f, 1e-4f);
    }
    for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
        const auto [o, i] = desc.layer_shape(k);
        const bool last = k + 1 == desc.layer_count();
        // He-uniform for ReLU layers, Xavier-uniform for the linear output layer.
        const float a = last ? std::sqrt(6.0f / float(i + o)) : std::sqrt(6.0f / float(i));
        w_.emplace_back(std::size_t(o) * i);
        for (float& x : w_.back()) x = rng.uniform(-a, a);
        b_.emplace_back(o, 0.0f);
    }
    Impl& im = *impl_;
    for (auto& g : grid_) {
        im.gm.emplace_back(g.size(), 0.0f);
        im.gv.emplace_back(g.size(), 0.0f);
        im.gsum.emplace_back(g.size(), 0.0f);
    }
    for (std::uint32_t l = 0; l < desc.level_count(); ++l) {
        im.row_step.emplace_back(desc.level_entries(l), 0u);
        im.active.emplace_back(desc.level_entries(l), 0u);
        im.gsum_norm2.emplace_back((desc.level_entries(l) + kNormBlock - 1) / kNormBlock, 0.0);
    }
    for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
        im.wm.emplace_back(w_[k].size(), 0.0f);
        im.wv.emplace_back(w_[k].size(), 0.0f);
        im.bm.emplace_back(b_[k].size(), 0.0f);
        im.bv.emplace_back(b_[k].size(), 0.0f);
        im.wgrad.emplace_back(w_[k].size(), 0.0f);
        im.bgrad.emplace_back(b_[k].size(), 0.0f);
    }
    std::uint32_t maxw = pad16(desc.input_width()), max_in32 = 0, max_out32 = 0, max_in16 = 0;
    for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
        const auto [o, i] = desc.layer_shape(k);
        maxw = std::max(maxw, pad16(o));
        max_in32 = std::max(max_in32, pad32(i));
        max_in16 = std::max(max_in16, pad16(i));
        max_out32 = std::max(max_out32, pad32(o));
    }
    im.zeros.assign(maxw, 0.0f);
    im.work.resize(threads_);
    for (Work& w : im.work) {
        w.pts.resize(kSub);
        w.x.resize(kSub * desc.input_width());
        for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
            const auto [o, i] = desc.layer_shape(k);
            w.act.emplace_back(kSub * pad16(o));
        }
        w.d0.resize(kSub * maxw);
        w.d1.resize(kSub * maxw);
        if (precision_ == MlpPrecision::bf16) {
            w.a_rows.resize(kSub * max_in32);
            w.a_t.resize(std::size_t(max_in16) * pad32(kSub));
            w.g_rows.resize(kSub * max_out32);
            w.g_vnni.resize(std::size_t(pad32(kSub)) * maxw);
        }
    }
    im.owned = owned_rows(desc, geo_, threads_);
}

Trainer::~Trainer() {
    delete impl_;
}

double Trainer::mlp_flops_per_sample() const {
    double f = 0;
    for (std::uint32_t k = 0; k < desc_.layer_count(); ++k) {
        const auto [o, i] = desc_.layer_shape(k);
        // forward, weight gradient, input gradient (not for the first layer's input
        // would be skippable, but the encoding needs it): 3 GEMMs of 2*o*i FLOPs.
        f += 3.0 * 2.0 * double(o) * double(i);
    }
    return f;
}

float Trainer::schedule(std::uint64_t step) const {
    const double s = double(step) / std::max(1u, cfg_.steps);
    if (s <= cfg_.decay_start) return 1.0f;
    const double u = std::min(1.0, (s - cfg_.decay_start) / std::max(1e-9, 1.0 - cfg_.decay_start));
    return float(base::pow(double(cfg_.final_lr_fraction), u));
}

std::vector<Sample> Trainer::reachable(std::span<const Sample> samples) const {
    std::vector<Sample> out;
    RayPoints pts;
    for (const Sample& s : samples)
        if (format::trace_points(geo_, occupancy_.data(), s.ray, pts) == TraceStatus::ok) out.push_back(s);
    return out;
}

namespace {

// Encodes rows 0..n-1 (n <= kSub) of the sub-chunk (w.pts) into w.x with the reader's
// batch encoder, so training and reading share one encoder: encode_points' values bit for
// bit (forward.hpp).
void encode_rows(const Geometry& geo, const std::vector<format::GridView>& grid, std::size_t n, Work& w) {
    static const std::vector<std::uint32_t> identity = [] {
        std::vector<std::uint32_t> v(kSub);
        for (std::uint32_t i = 0; i < kSub; ++i) v[i] = i;
        return v;
    }();
    format::encode_batch(geo, grid.data(), w.pts.data(), std::span(identity).first(n), w.x.data());
}

// Describes the first layer's zero inputs of rows 0..n-1 (n <= kSub) of the sub-chunk from
// their point counts (w.pts): the empty slots' features [count L F, point_width) and, where the
// model has entry offsets, the empty slots' offsets; and, per input column, how many leading
// rows may hold a nonzero value there (w.live_rows; exact when the rows come in decreasing
// point count, as loss_and_gradients orders them, and merely loose otherwise).
void empty_inputs(const Geometry& geo, std::size_t n, Work& w) {
    const std::uint32_t per_point = geo.L * geo.F;
    w.lead.resize(n);
    w.rest.resize(n);
    std::uint32_t counted[format::kMaxPoints + 1] = {};  // rows with count > h, as h goes down
    for (std::size_t r = 0; r < n; ++r) {
        const std::uint32_t count = w.pts[r].count;
        w.lead[r] = count * per_point;
        w.rest[r] = count;
        ++counted[count];
    }
    std::uint32_t more_than[format::kMaxPoints + 1] = {};
    for (std::uint32_t h = geo.H, above = 0; h-- > 0;) {
        above += counted[h + 1];
        more_than[h] = above;
    }
    const std::size_t rest_start = std::size_t(geo.point_width) + geo.direction_width;
    w.live_rows.resize(geo.input_width);
    for (std::size_t c = 0; c < geo.input_width; ++c)
        w.live_rows[c] = c < geo.point_width ? more_than[c / per_point]
                         : c < rest_start    ? std::uint32_t(n)
                                             : more_than[c - rest_start];
    w.zeros = {w.lead.data(), geo.point_width, geo.offset_width ? w.rest.data() : nullptr, rest_start};
}

// Encoding and layers for rows whose w.pts are filled. Rows whose ray does not reach the
// network have count = 0 (all-zero point features). The first layer skips the inputs of
// empty slots (empty_inputs): the same bits, since ReLU follows.
void forward_layers(const Geometry& geo, const std::vector<format::GridView>& grid,
                    const format::Network& net, std::size_t n, Work& w) {
    encode_rows(geo, grid, n, w);
    empty_inputs(geo, n, w);
    const float* src = w.x.data();
    std::size_t lda = geo.input_width;
    for (std::size_t k = 0; k < net.wt.size(); ++k) {
        const bool hidden = k + 1 < net.wt.size();
        format::dense_layer_strided(src, n, net.in[k], lda, net.wt[k].data(), net.out_padded[k],
                                    net.bias[k].data(), net.out_padded[k], hidden, w.act[k].data(),
                                    net.out_padded[k], k == 0 ? &w.zeros : nullptr);
        src = w.act[k].data();
        lda = net.out_padded[k];
    }
}

// forward_layers with the hidden layers' products in bf16 on AMX (MlpPrecision::bf16):
// each hidden layer's input is rounded to bf16 rows, multiplied by the VNNI-packed weights
// `wf` into w.act (fp32), then bias and ReLU are applied in fp32.
// The output layer's forward stays fp32 (format::dense_layer, ~2% of the MLP FLOPs; its two
// backward products are bf16 like the others): the loss gradients depend on residuals
// (distance error against a 1%-of-diagonal Huber delta) far smaller than the outputs, so
// rounding its inputs to bf16 would move them by tens of percent late in training, far more
// than bf16 moves any other gradient (test_amx.cpp compares them with fp32;
// docs/investigations/training-and-inference-throughput.md).
void forward_layers_bf16(const Geometry& geo, const std::vector<format::GridView>& grid,
                         const format::Network& net, const std::vector<detail::Bf16Buffer>& wf, std::size_t n,
                         Work& w) {
    encode_rows(geo, grid, n, w);
    const float* src = w.x.data();
    std::size_t lda = geo.input_width;
    for (std::size_t k = 0; k < net.wt.size(); ++k) {
        const std::size_t in = net.in[k], kp = pad32(net.in[k]), outp = net.out_padded[k];
        if (k + 1 == net.wt.size()) {
            format::dense_layer(src, n, in, lda, net.wt[k].data(), net.bias[k].data(), outp, false,
                                w.act[k].data());
            break;
        }
        detail::pack_rows(src, n, in, lda, w.a_rows.data(), kp, detail::round_up(n, 16));
        float* dst = w.act[k].data();
        detail::gemm_bf16(n, outp, kp, w.a_rows.data(), kp, wf[k].data(), 2 * outp, dst, outp, false);
        const float* bias = net.bias[k].data();
        for (std::size_t r = 0; r < n; ++r) {
            float* row = dst + r * outp;
            for (std::size_t o = 0; o < outp; ++o) row[o] = std::max(row[o] + bias[o], 0.0f);
        }
        src = dst;
        lda = outp;
    }
}

// Forward of one sub-chunk of raw samples: trace, then forward_layers. Rays that do not
// reach the network get count = 0.
void forward_chunk(const Geometry& geo, const std::uint8_t* occ, const std::vector<format::GridView>& grid,
                   const format::Network& net, std::span<const Sample> rows, Work& w) {
    for (std::size_t r = 0; r < rows.size(); ++r)
        if (format::trace_points(geo, occ, rows[r].ray, w.pts[r]) != TraceStatus::ok) w.pts[r].count = 0;
    forward_layers(geo, grid, net, rows.size(), w);
}

}  // namespace

std::vector<float> Trainer::predict_raw(std::span<const Sample> batch) {
    Impl& im = *impl_;
    im.net = format::make_network(desc_, w_, b_);
    std::vector<format::GridView> gp;
    for (auto& g : grid_) gp.push_back({g.data(), geo_.F, format::GridElement::f32});
    const std::uint32_t outs = desc_.output_count();
    std::vector<float> out(batch.size() * outs);
    Work& w = im.work[0];
    for (std::size_t base = 0; base < batch.size(); base += kSub) {
        const std::size_t n = std::min(kSub, batch.size() - base);
        forward_chunk(geo_, occupancy_.data(), gp, im.net, batch.subspan(base, n), w);
        const std::size_t outp = im.net.out_padded.back();
        for (std::size_t r = 0; r < n; ++r)
            std::memcpy(out.data() + (base + r) * outs, w.act.back().data() + r * outp, outs * sizeof(float));
    }
    return out;
}

PreparedSet Trainer::prepare(std::span<const Sample> samples) const {
    PreparedSet set;
    prepare_append(samples, set);
    return set;
}

void Trainer::prepare_append(std::span<const Sample> samples, PreparedSet& set) const {
    const std::uint32_t H = geo_.H;
    const format::OccupancyGrid occ_grid(geo_.V, occupancy_);  // block skipping; same points
    Impl::PrepareScratch& sc = impl_->prep;
    sc.ok.resize(samples.size());
    sc.count.resize(samples.size());
    sc.tn.resize(samples.size());
    sc.tf.resize(samples.size());
    sc.t0.resize(samples.size());
    sc.g.resize(samples.size() * H * 3);
    auto& ok = sc.ok;
    auto& count = sc.count;
    auto& tn = sc.tn;
    auto& tf = sc.tf;
    auto& t0 = sc.t0;
    auto& g = sc.g;
    const std::size_t per = (samples.size() + threads_ - 1) / threads_;
    parallel(threads_, [&](std::uint32_t t) {
        // Batches for the 16-lane walk, small enough that the points stay in L2.
        constexpr std::size_t kBatch = 64;
        std::vector<format::Ray> rays(kBatch);
        std::vector<RayPoints> pts(kBatch);
        std::vector<TraceStatus> status(kBatch);
        const std::size_t b = std::min(samples.size(), t * per), e = std::min(samples.size(), b + per);
        for (std::size_t i0 = b; i0 < e; i0 += kBatch) {
            const std::size_t n = std::min(kBatch, e - i0);
            for (std::size_t k = 0; k < n; ++k) rays[k] = samples[i0 + k].ray;
            format::trace_points_batch(geo_, occ_grid, std::span(rays).first(n), pts.data(), status.data());
            for (std::size_t k = 0; k < n; ++k) {
                const std::size_t i = i0 + k;
                const RayPoints& p = pts[k];
                ok[i] = status[k] == TraceStatus::ok;
                if (!ok[i]) continue;
                count[i] = std::uint16_t(p.count);
                tn[i] = p.t_near;
                tf[i] = p.t_far;
                t0[i] = p.t[0];
                std::memcpy(&g[i * H * 3], p.g, sizeof(float) * 3 * p.count);
            }
        }
    });
    // Compaction in parallel, in sample order: each thread's kept samples go after those of
    // the threads before it: a serial copy of the H x 3 points per sample would be the
    // largest serial part of prepare().
    std::vector<std::size_t> kept(threads_ + 1, 0);
    parallel(threads_, [&](std::uint32_t t) {
        const std::size_t b = std::min(samples.size(), t * per), e = std::min(samples.size(), b + per);
        std::size_t n = 0;
        for (std::size_t i = b; i < e; ++i) n += ok[i];
        kept[t + 1] = n;
    });
    kept[0] = set.size();  // appended after the samples already in the set
    for (std::uint32_t t = 0; t < threads_; ++t) kept[t + 1] += kept[t];
    set.H = H;
    const std::size_t n = kept[threads_];
    set.samples.resize(n);
    set.count.resize(n);
    set.t_near.resize(n);
    set.t_far.resize(n);
    set.t_first.resize(n);
    set.g.resize(n * H * 3);
    parallel(threads_, [&](std::uint32_t t) {
        const std::size_t b = std::min(samples.size(), t * per), e = std::min(samples.size(), b + per);
        std::size_t j = kept[t];
        for (std::size_t i = b; i < e; ++i) {
            if (!ok[i]) continue;
            set.samples[j] = samples[i];
            set.count[j] = count[i];
            set.t_near[j] = tn[i];
            set.t_far[j] = tf[i];
            set.t_first[j] = t0[i];
            std::memcpy(&set.g[j * H * 3], &g[i * H * 3], sizeof(float) * 3 * count[i]);
            ++j;
        }
    });
}

LossParts Trainer::loss_and_gradients(std::span<const Sample> batch, Gradients* grads) {
    const PreparedSet set = prepare(batch);
    std::vector<std::uint32_t> idx(set.size());
    for (std::size_t i = 0; i < idx.size(); ++i) idx[i] = std::uint32_t(i);
    return loss_and_gradients(set, idx, grads);
}

float Trainer::step(std::span<const Sample> batch) {
    const PreparedSet set = prepare(batch);
    std::vector<std::uint32_t> idx(set.size());
    for (std::size_t i = 0; i < idx.size(); ++i) idx[i] = std::uint32_t(i);
    return step(set, idx);
}

TrainResult Trainer::train(std::span<const Sample> samples, const ProgressFn& progress) {
    return train(prepare(samples), progress);
}

namespace {

// Per-batch constants of the losses: the loss is a mean over the batch (visibility) or
// over its true hits (the other terms), each term scaled by its weight.
struct LossScale {
    float inv_b;  // 1 / batch size
    float inv_h;  // 1 / true hits in the batch
    LossWeights weight;
    float huber_delta;
    NormalLoss normal_loss;
    float chord_epsilon;
    std::uint32_t materials;
};

// Visibility: binary cross-entropy with logits, softplus(z) - y z in its stable form.
void visibility_loss(const Sample& s, const float* o, const LossScale& k, LossParts& loss, float* g) {
    const float y = s.hit ? 1.0f : 0.0f, z = o[OutputLayout::visibility];
    loss.visibility +=
        (double(std::max(z, 0.0f) - z * y) + base::log1p(base::exp(-std::fabs(double(z))))) * k.inv_b;
    g[OutputLayout::visibility] = k.weight.visibility * (sigmoid(z) - y) * k.inv_b;
}

// Distance: Huber loss (quadratic below huber_delta) on the encoded distance, whose target
// is format::encode_distance of the true hit.
void distance_loss(const Geometry& geo, const Sample& s, const RayPoints& p, const float* o,
                   const LossScale& k, LossParts& loss, float* g) {
    const float dlen =
        std::sqrt(s.ray.dir[0] * s.ray.dir[0] + s.ray.dir[1] * s.ray.dir[1] + s.ray.dir[2] * s.ray.dir[2]);
    const float e = o[OutputLayout::distance] - format::encode_distance(geo, p, dlen, s.t);
    const float ae = std::fabs(e), delta = k.huber_delta;
    loss.distance += double(ae < delta ? 0.5f * e * e / delta : ae - 0.5f * delta) * k.inv_h;
    g[OutputLayout::distance] = k.weight.distance * std::clamp(e / delta, -1.0f, 1.0f) * k.inv_h;
}

// Normal: a function of c = cos(angle) between the raw output and the unit target normal
// (NormalLoss): 1 - c, or the smoothed chord q - ε with q = sqrt(2 (1 - c) + ε²), whose
// derivative in c is -1/q; plus the hinge max(0, -n·t) on the raw output n, quadratic below
// kNormalHingeKnee so that the loss stays smooth where c crosses 0.
//
// Why the hinge: a function of c alone does not change when the output is scaled, so its
// gradient is tangent to the sphere and vanishes at c = -1. On a thin part (a closed
// object 1/500 as thick as wide) the rays that hit either side pass through the same
// cells; a network that first learns one orientation for both sides then sits at c = -1 on
// half of them and never flips (docs/model.md "The normal loss"). The hinge's gradient,
// -t, does not depend on n: it shrinks a wrong-hemisphere output toward the origin and
// out the target's side, and is zero once c >= 0, so it leaves the shape's behaviour on
// well-oriented predictions alone.
constexpr float kNormalHingeKnee = 0.05f;  // the hinge is quadratic below this (smooth at c = 0)
void normal_loss(const Sample& s, const float* o, const LossScale& k, LossParts& loss, float* g) {
    const float* n = o + OutputLayout::normal;
    const float len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) + 1e-12f;
    const float c = (n[0] * s.normal[0] + n[1] * s.normal[1] + n[2] * s.normal[2]) / len;
    float dc = 1.0f;  // -dL/dc
    if (k.normal_loss == NormalLoss::chord) {
        const float eps = k.chord_epsilon;
        const float q = std::sqrt(2.0f * std::max(0.0f, 1.0f - c) + eps * eps);
        loss.normal += double(q - eps) * k.inv_h;
        dc = 1.0f / q;
    } else {
        loss.normal += double(1.0f - c) * k.inv_h;
    }
    for (int a = 0; a < 3; ++a)
        g[OutputLayout::normal + a] =
            -dc * k.weight.normal * k.inv_h * (s.normal[a] / len - c * n[a] / (len * len));
    const float x = -c * len;  // -n·t: how far the raw output reaches into the wrong hemisphere
    if (x > 0.0f) {
        const float delta = kNormalHingeKnee;
        const float slope = std::min(x / delta, 1.0f);
        loss.normal += double(x < delta ? 0.5f * x * x / delta : x - 0.5f * delta) * k.inv_h;
        for (int a = 0; a < 3; ++a)
            g[OutputLayout::normal + a] -= slope * k.weight.normal * k.inv_h * s.normal[a];
    }
}

// Material: softmax cross-entropy over the material logits (materials > 0).
void material_loss(const Sample& s, const float* o, const LossScale& k, LossParts& loss, float* g) {
    const std::uint32_t M = k.materials;
    const float* logit = o + OutputLayout::material;
    float mx = logit[0];
    for (std::uint32_t m = 1; m < M; ++m) mx = std::max(mx, logit[m]);
    double sum = 0;
    for (std::uint32_t m = 0; m < M; ++m) sum += base::exp(double(logit[m] - mx));
    const std::uint32_t target = std::min(s.material, M - 1);
    loss.material += (base::log(sum) - double(logit[target] - mx)) * k.inv_h;
    for (std::uint32_t m = 0; m < M; ++m)
        g[OutputLayout::material + m] =
            k.weight.material * k.inv_h *
            (float(base::exp(double(logit[m] - mx)) / sum) - (m == target ? 1.0f : 0.0f));
}

// The losses of n output rows (stride outp) into w.loss, and dL/d(output) into dO (n x
// outp, padding columns zero). Rays that miss, or that no voxel entry point reaches, train
// visibility only.
void output_losses(const Geometry& geo, const PreparedSet& set, std::span<const std::uint32_t> rows,
                   const float* out, std::size_t outp, const LossScale& k, const Work& w, LossParts& loss,
                   float* dO) {
    std::memset(dO, 0, rows.size() * outp * sizeof(float));
    for (std::size_t r = 0; r < rows.size(); ++r) {
        const Sample& s = set.samples[rows[r]];
        const float* o = out + r * outp;
        float* g = dO + r * outp;
        visibility_loss(s, o, k, loss, g);
        const RayPoints& p = w.pts[r];
        if (!s.hit || p.count == 0) continue;
        distance_loss(geo, s, p, o, k, loss, g);
        normal_loss(s, o, k, loss, g);
        if (k.materials > 0) material_loss(s, o, k, loss, g);
    }
}

// `rows` in decreasing point count (set.count), equal counts in batch order: a counting sort,
// the same order on every machine. Blocks of rows then share their runs of empty slots,
// which the first layer skips (empty_inputs).
void order_by_count(const PreparedSet& set, std::span<const std::uint32_t> rows, std::uint32_t H,
                    std::vector<std::uint32_t>& out) {
    std::uint32_t start[format::kMaxPoints + 2] = {};
    for (const std::uint32_t i : rows) ++start[H - set.count[i] + 1];
    for (std::uint32_t c = 1; c <= H + 1; ++c) start[c] += start[c - 1];
    out.resize(rows.size());
    for (const std::uint32_t i : rows) out[start[H - set.count[i]]++] = i;
}

// Fills w.pts[0..rows) from the prepared set: the entry points were traced once, so no DDA.
// The rows are random draws from a set of hundreds of MB: their Sample records, which the
// losses read after the forward pass, are requested first so the misses overlap.
void load_points(const PreparedSet& set, std::span<const std::uint32_t> rows, Work& w) {
    for (const std::uint32_t i : rows) {
        __builtin_prefetch(&set.samples[i]);
        __builtin_prefetch(reinterpret_cast<const char*>(&set.samples[i] + 1) - 1);
    }
    for (std::size_t r = 0; r < rows.size(); ++r) {
        const std::uint32_t i = rows[r];
        RayPoints& p = w.pts[r];
        p.count = set.count[i];
        p.t_near = set.t_near[i];
        p.t_far = set.t_far[i];
        p.t[0] = set.t_first[i];
        std::memcpy(p.g, &set.g[std::size_t(i) * set.H * 3], sizeof(float) * 3 * p.count);
        format::unit_direction(set.samples[i].ray, p.dir);
    }
}

// Appends the n rows' entry points (w.pts) and dL/d(point features) (dx: n rows of stride
// ldx, each holding at least its points' features) to c.point_grads, for
// Impl::scatter_grid_gradients after the pass.
void record_point_gradients(const Geometry& geo, const float* dx, std::size_t ldx, std::size_t n,
                            const Work& w, ChunkResult& c) {
    const std::size_t ip0 = ldx, per_point = std::size_t(geo.L) * geo.F;
    for (std::size_t r = 0; r < n; ++r) {
        const RayPoints& p = w.pts[r];
        const std::size_t at = c.point_grads.size();
        c.point_grads.resize(at + p.count * (3 + per_point));
        float* out = c.point_grads.data() + at;
        std::memcpy(out, p.g, sizeof(float) * 3 * p.count);
        std::memcpy(out + 3 * p.count, dx + r * ip0, sizeof(float) * per_point * p.count);
        c.point_counts.push_back(std::uint16_t(p.count));
    }
}

// Sum of x[i]^2 in double over 8 interleaved partial sums: a fixed order (the result
// depends only on x), and one that vectorizes instead of waiting on a single running sum.
double sum_of_squares(const float* x, std::size_t n) {
    double part[8] = {};
    std::size_t i = 0;
    for (; i + 8 <= n; i += 8)
        for (std::size_t k = 0; k < 8; ++k) part[k] += double(x[i + k]) * double(x[i + k]);
    double sum = 0;
    for (const double p : part) sum += p;
    for (; i < n; ++i) sum += double(x[i]) * double(x[i]);
    return sum;
}

// Points of the scatter, 16 at a time: their grid coordinates (structure of arrays, what
// level_corners16 reads), where their feature gradients on the level are, and their corners.
struct ScatterBatch {
    alignas(64) float x[16], y[16], z[16];
    const float* src[16];
    std::uint32_t count = 0;
    format::Corners16 corners;
};

// Adds each sample's corner shares on level `level` into rows [first, last) of `table`
// (rows x F) and marks them in `active`, the samples in the order `chunks` recorded them. Only
// corners that carry weight are visited. The corners are computed 16 points at a time
// (level_corners16) and software-pipelined by one batch: a batch's corners are computed and
// their rows prefetched (the table exceeds L2) while the previous batch's shares are added,
// so each row has a batch's worth of work to arrive. The shares are added point by point,
// corner by corner, in the order level_corners gives them: the sums do not depend on the
// batching.
void scatter_level(const Geometry& geo, std::uint32_t level, std::pair<std::size_t, std::size_t> rows,
                   std::span<const ChunkResult> chunks, float* table, std::uint8_t* active) {
    const std::uint32_t L = geo.L, F = geo.F;
    const format::LevelInfo& lv = geo.levels[level];
    const auto [first, last] = rows;
    const auto owned = [&](std::uint32_t index) { return index >= first && index < last; };
    const auto stage = [&](ScatterBatch& b) {
        format::level_corners16(geo, lv, b.x, b.y, b.z, b.count, b.corners);
        const format::Corners16& c = b.corners;
        for (std::uint32_t j = 0; j < b.count; ++j)
            for (std::uint32_t q = 0; q < c.n[j]; ++q)
                if (owned(c.index[q][j])) __builtin_prefetch(table + std::size_t(c.index[q][j]) * F, 1);
    };
    // dst[f] += weight * src[f] for f < F. The presets' F = 3 spelled out: the loop over a
    // run-time F paid for its bounds and for checks that dst and src do not overlap on every
    // corner. Same statement per feature, so the same rounding.
    const auto add_share = [F](float* dst, float weight, const float* src) {
        if (F == 3) {
            const float s0 = src[0], s1 = src[1], s2 = src[2];
            dst[0] += weight * s0;
            dst[1] += weight * s1;
            dst[2] += weight * s2;
            return;
        }
        for (std::uint32_t f = 0; f < F; ++f) dst[f] += weight * src[f];
    };
    const auto add = [&](const ScatterBatch& b) {
        const format::Corners16& c = b.corners;
        for (std::uint32_t j = 0; j < b.count; ++j) {
            const float* src = b.src[j];
            for (std::uint32_t q = 0; q < c.n[j]; ++q) {
                const std::uint32_t index = c.index[q][j];
                if (!owned(index)) continue;
                add_share(table + std::size_t(index) * F, c.weight[q][j], src);
                active[index] = 1;
            }
        }
    };
    ScatterBatch batch[2];
    std::uint32_t cur = 0;
    bool pending = false;  // batch[cur ^ 1] is staged and its shares are not added yet
    for (const ChunkResult& w : chunks) {
        const float* rec = w.point_grads.data();
        for (const std::uint16_t count : w.point_counts) {
            const float* dx = rec + 3 * count;
            for (std::uint32_t h = 0; h < count; ++h) {
                ScatterBatch& b = batch[cur];
                b.x[b.count] = rec[3 * h];
                b.y[b.count] = rec[3 * h + 1];
                b.z[b.count] = rec[3 * h + 2];
                b.src[b.count++] = dx + (std::size_t(h) * L + level) * F;
                if (b.count < 16) continue;
                stage(b);
                if (pending) add(batch[cur ^ 1]);
                pending = true;
                cur ^= 1;
                batch[cur].count = 0;
            }
            rec += count * (3 + std::size_t(L) * F);
        }
    }
    if (batch[cur].count) stage(batch[cur]);
    if (pending) add(batch[cur ^ 1]);
    if (batch[cur].count) add(batch[cur]);
}

}  // namespace

void Trainer::Impl::stage_weights(const format::ModelDesc& desc, const std::vector<std::vector<float>>& w,
                                  bool bf16) {
    const std::uint32_t layers = desc.layer_count();
    if (bf16) {  // B operands of this step's products: forward Wt (K = in), backward W (K = out)
        wf.resize(layers);
        wb.resize(layers);
        for (std::uint32_t k = 0; k < layers; ++k) {
            const auto [o, i] = desc.layer_shape(k);
            const std::size_t op = net.out_padded[k], ip = pad16(i);
            if (k + 1 < layers) {  // the output layer's forward stays fp32
                wf[k].resize(std::size_t(pad32(i)) * op);
                detail::pack_vnni(net.wt[k].data(), i, op, op, wf[k].data(), 2 * op, pad32(i));
            }
            wb[k].resize(std::size_t(pad32(o)) * ip);
            detail::pack_vnni(w[k].data(), o, i, i, wb[k].data(), 2 * ip, pad32(o));
        }
        return;
    }
    wpad.resize(layers);
    for (std::uint32_t k = 0; k < layers; ++k) {
        const auto [o, i] = desc.layer_shape(k);
        const std::uint32_t ip = pad16(i);
        wpad[k].assign(std::size_t(o) * ip, 0.0f);
        for (std::uint32_t r = 0; r < o; ++r)
            std::memcpy(wpad[k].data() + std::size_t(r) * ip, w[k].data() + std::size_t(r) * i,
                        i * sizeof(float));
    }
}

float* Trainer::Impl::mlp_backward(const Geometry& geo, std::size_t n, bool bf16, Work& w, ChunkResult& c,
                                   std::size_t& ld) const {
    float* G = w.d0.data();
    float* other = w.d1.data();
    ld = pad16(geo.input_width);
    for (int k = int(net.wt.size()) - 1; k >= 0; --k) {
        const std::size_t outp_k = net.out_padded[k];
        const std::size_t in_k = net.in[k];
        const float* X = k == 0 ? w.x.data() : w.act[k - 1].data();
        const std::size_t ldx = k == 0 ? geo.input_width : net.out_padded[k - 1];
        const std::size_t ip = pad16(std::uint32_t(in_k));
        if (bf16) {
            // dWt += X^T G: A = X^T (rows = inputs, K = samples), B = G by row pairs.
            const std::size_t np = detail::round_up(n, 32);
            detail::pack_transposed(X, n, in_k, ldx, w.a_t.data(), np, ip);
            detail::pack_vnni(G, n, outp_k, outp_k, w.g_vnni.data(), 2 * outp_k, np);
            detail::gemm_bf16(ip, outp_k, np, w.a_t.data(), np, w.g_vnni.data(), 2 * outp_k, c.dwt[k].data(),
                              outp_k, true);
            // dX = G W (K = the real outputs, zero-padded to 32).
            const std::size_t kp = pad32(net.out[k]);
            detail::pack_rows(G, n, net.out[k], outp_k, w.g_rows.data(), kp, detail::round_up(n, 16));
            detail::gemm_bf16(n, ip, kp, w.g_rows.data(), kp, wb[k].data(), 2 * ip, other, ip, false);
        } else if (k > 0) {
            detail::outer_accumulate(X, n, in_k, ldx, G, outp_k, c.dwt[k].data());
            // dX = G W (contract over the real outputs; padded columns of G are zero).
            format::dense_layer(G, n, net.out[k], outp_k, wpad[k].data(), zeros.data(), ip, false, other);
        } else {
            // The first layer: a column's rows past w.live_rows hold zero inputs and add
            // nothing to dW (but the sign of a zero sum, which the chunks' reduction from +0
            // normalizes); dX only for the point features of the fullest row (the first:
            // rows come in decreasing point count), the only inputs with parameters behind.
            detail::outer_accumulate(X, n, in_k, ldx, G, outp_k, c.dwt[0].data(), w.live_rows.data());
            const std::size_t cols = pad16(w.lead[0]);
            format::dense_layer_strided(G, n, net.out[0], outp_k, wpad[0].data(), ip, zeros.data(), cols,
                                        false, other, cols, nullptr);
            ld = cols;
        }
        for (std::size_t r = 0; r < n; ++r)
            for (std::size_t o = 0; o < outp_k; ++o) c.db[k][o] += G[r * outp_k + o];
        if (k > 0) {  // ReLU derivative of the previous layer's output
            const float* H = w.act[k - 1].data();
            for (std::size_t q = 0; q < n * ip; ++q)
                if (!(H[q] > 0.0f)) other[q] = 0.0f;
        }
        std::swap(G, other);
    }
    return G;
}

void Trainer::Impl::prepare_chunks(const format::ModelDesc& desc, std::size_t count) {
    while (chunks.size() < count) {
        ChunkResult& c = chunks.emplace_back();
        for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
            const auto [o, i] = desc.layer_shape(k);
            // pad16(i) rows: the bf16 weight-gradient product covers whole 16-row tiles (the
            // extra rows stay zero; reductions read the first i).
            c.dwt.emplace_back(std::size_t(pad16(i)) * pad16(o), 0.0f);
            c.db.emplace_back(pad16(o), 0.0f);
        }
    }
}

void Trainer::Impl::reduce_mlp_gradients(const format::ModelDesc& desc, std::size_t count,
                                         std::uint32_t threads) {
    const std::uint32_t layers = desc.layer_count();
    // Thread t sums the inputs [t i / T, (t + 1) i / T) of every layer: one row of dWt per
    // input, over the chunks in order.
    base::run_on_threads(threads, [&](std::uint32_t t) {
        std::vector<float> row;
        for (std::uint32_t k = 0; k < layers; ++k) {
            const auto [o, i] = desc.layer_shape(k);
            const std::size_t op = net.out_padded[k];
            row.resize(op);
            const std::size_t first = std::size_t(i) * t / threads, last = std::size_t(i) * (t + 1) / threads;
            for (std::size_t ii = first; ii < last; ++ii) {
                std::fill(row.begin(), row.end(), 0.0f);
                for (std::size_t c = 0; c < count; ++c) {
                    float* src = chunks[c].dwt[k].data() + ii * op;
                    for (std::size_t oo = 0; oo < op; ++oo) row[oo] += src[oo];
                    std::fill_n(src, op, 0.0f);
                }
                for (std::uint32_t oo = 0; oo < o; ++oo) wgrad[k][std::size_t(oo) * i + ii] = row[oo];
            }
        }
    });
    for (std::uint32_t k = 0; k < layers; ++k) {
        const std::uint32_t o = desc.layer_shape(k).first;
        std::fill(bgrad[k].begin(), bgrad[k].end(), 0.0f);
        for (std::size_t c = 0; c < count; ++c) {
            for (std::uint32_t oo = 0; oo < o; ++oo) bgrad[k][oo] += chunks[c].db[k][oo];
            std::fill(chunks[c].db[k].begin(), chunks[c].db[k].end(), 0.0f);
        }
    }
}

void Trainer::Impl::scatter_grid_gradients(const Geometry& geo, std::size_t count) {
    const auto T = std::uint32_t(owned.size());
    const std::span<const ChunkResult> results(chunks.data(), count);
    base::run_on_threads(T, [&](std::uint32_t t) {
        for (std::uint32_t l = 0; l < geo.L; ++l) {
            const auto [first, last] = owned[t][l];
            if (first == last) continue;
            scatter_level(geo, l, owned[t][l], results, gsum[l].data(), active[l].data());
            // Rows without gradient are zero, so whole blocks can be summed.
            for (std::size_t b = first; b < last; b += kNormBlock)
                gsum_norm2[l][b / kNormBlock] =
                    sum_of_squares(gsum[l].data() + b * geo.F, (std::min(last, b + kNormBlock) - b) * geo.F);
        }
    });
}

double Trainer::Impl::grid_norm2() const {
    double sum = 0;
    for (const auto& level : gsum_norm2)
        for (const double block : level) sum += block;
    return sum;
}

void Trainer::Impl::clear_grid_gradients(std::uint32_t F) {
    for (std::size_t l = 0; l < active.size(); ++l)
        for (std::size_t row = 0; row < active[l].size(); ++row) {
            if (!active[l][row]) continue;
            std::fill_n(gsum[l].data() + row * F, F, 0.0f);
            active[l][row] = 0;
        }
}

void Trainer::Impl::export_gradients(std::uint32_t F, Gradients& grads) {
    grads.grid = gsum;
    grads.weights = wgrad;
    grads.biases = bgrad;
    clear_grid_gradients(F);
}

LossParts Trainer::loss_and_gradients(const PreparedSet& set, std::span<const std::uint32_t> batch,
                                      Gradients* grads) {
    Impl& im = *impl_;
    im.net = format::make_network(desc_, w_, b_);
    const bool bf16 = precision_ == MlpPrecision::bf16;
    im.stage_weights(desc_, w_, bf16);
    std::vector<format::GridView> gp;
    for (auto& g : grid_) gp.push_back({g.data(), geo_.F, format::GridElement::f32});

    const std::size_t B = batch.size();
    std::size_t hits = 0;
    for (std::uint32_t i : batch) hits += set.samples[i].hit != 0;
    const LossScale scale{1.0f / float(std::max<std::size_t>(1, B)),
                          1.0f / float(std::max<std::size_t>(1, hits)),
                          cfg_.loss,
                          cfg_.huber_delta,
                          cfg_.normal_loss,
                          cfg_.normal_chord_epsilon,
                          desc_.material_count};
    // Chunks of the batch (chunk_rows: a function of B alone), handed out to the threads
    // dynamically; each chunk's rows run in order, sub-chunk by sub-chunk.
    const std::size_t per = chunk_rows(B), count = (B + per - 1) / per;
    im.prepare_chunks(desc_, count);
    std::atomic<std::size_t> next{0};
    parallel(std::uint32_t(std::min<std::size_t>(threads_, count)), [&](std::uint32_t t) {
        Work& w = im.work[t];
        for (std::size_t c; (c = next.fetch_add(1, std::memory_order_relaxed)) < count;) {
            ChunkResult& chunk = im.chunks[c];
            chunk.loss = LossParts{};
            chunk.point_grads.clear();
            chunk.point_counts.clear();
            const std::size_t begin = c * per, end = std::min(B, begin + per);
            order_by_count(set, batch.subspan(begin, end - begin), geo_.H, w.order);
            for (std::size_t base = 0; base < end - begin; base += kSub) {
                const std::size_t n = std::min(kSub, end - begin - base);
                const auto rows = std::span<const std::uint32_t>(w.order).subspan(base, n);
                load_points(set, rows, w);
                if (bf16)
                    forward_layers_bf16(geo_, gp, im.net, im.wf, n, w);
                else
                    forward_layers(geo_, gp, im.net, n, w);
                output_losses(geo_, set, rows, w.act.back().data(), im.net.out_padded.back(), scale, w,
                              chunk.loss, w.d0.data());
                std::size_t ldx = 0;
                const float* dx = im.mlp_backward(geo_, n, bf16, w, chunk, ldx);
                record_point_gradients(geo_, dx, ldx, n, w, chunk);
            }
        }
    });

    // Every reduction in chunk order.
    const LossWeights& lw = cfg_.loss;
    LossParts total;
    for (std::size_t c = 0; c < count; ++c) {
        const LossParts& part = im.chunks[c].loss;
        total.visibility += part.visibility;
        total.distance += part.distance;
        total.normal += part.normal;
        total.material += part.material;
    }
    total.total = lw.visibility * total.visibility + lw.distance * total.distance + lw.normal * total.normal +
                  lw.material * total.material;
    im.reduce_mlp_gradients(desc_, count, threads_);
    im.scatter_grid_gradients(geo_, count);
    if (grads) im.export_gradients(geo_.F, *grads);
    return total;
}

void Trainer::snapshot() {
    Impl& im = *impl_;
    im.snap = {grid_, w_, b_, im.gm, im.gv, im.wm, im.wv, im.bm, im.bv, im.row_step, step_, im.ema, true};
}

void Trainer::rollback() {
    Impl& im = *impl_;
    if (!im.snap.valid) return;
    grid_ = im.snap.grid;
    w_ = im.snap.w;
    b_ = im.snap.b;
    im.gm = im.snap.gm;
    im.gv = im.snap.gv;
    im.wm = im.snap.wm;
    im.wv = im.snap.wv;
    im.bm = im.snap.bm;
    im.bv = im.snap.bv;
    im.row_step = im.snap.row_step;
    step_ = im.snap.step;
    im.ema = im.snap.ema;
}

float Trainer::step(const PreparedSet& set, std::span<const std::uint32_t> batch) {
    Impl& im = *impl_;
    if (!im.snap.valid) snapshot();
    const LossParts lp = loss_and_gradients(set, batch, nullptr);
    const std::uint32_t L = geo_.L, F = geo_.F;
    // Global gradient norm, in a fixed order (independent of the thread count).
    double norm2 = 0;
    for (const auto& g : im.wgrad) norm2 += sum_of_squares(g.data(), g.size());
    for (const auto& g : im.bgrad) norm2 += sum_of_squares(g.data(), g.size());
    norm2 += im.grid_norm2();
    const float loss = float(lp.total);
    const bool warm = step_ >= 20;
    const bool bad = !std::isfinite(loss) || !std::isfinite(norm2) ||
                     (warm && im.ema > 0 && loss > cfg_.divergence_factor * im.ema);
    if (bad) {
        im.clear_grid_gradients(F);
        rollback();
        lr_scale_ *= 0.5f;
        ++rollbacks_;
        return NAN;
    }
    im.ema = step_ == 0 ? loss : 0.95 * im.ema + 0.05 * loss;
    // These parameters just produced a healthy loss: that is the state worth keeping.
    if (cfg_.snapshot_interval && step_ % cfg_.snapshot_interval == 0) snapshot();
    const double norm = std::sqrt(norm2);
    const float scale =
        (cfg_.grad_clip_norm > 0 && norm > cfg_.grad_clip_norm) ? float(cfg_.grad_clip_norm / norm) : 1.0f;
    const float lr_factor = schedule(step_) * lr_scale_;
    ++step_;
    for (std::uint32_t k = 0; k < desc_.layer_count(); ++k) {
        adam_update(w_[k].data(), im.wm[k].data(), im.wv[k].data(), im.wgrad[k].data(), w_[k].size(),
                    std::uint32_t(step_), cfg_.mlp_adam.lr * lr_factor, scale, cfg_.mlp_adam);
        AdamConfig nol2 = cfg_.mlp_adam;
        nol2.l2 = 0.0f;  // biases are not regularized
        adam_update(b_[k].data(), im.bm[k].data(), im.bv[k].data(), im.bgrad[k].data(), b_[k].size(),
                    std::uint32_t(step_), cfg_.mlp_adam.lr * lr_factor, scale, nol2);
    }
    const float grid_lr = cfg_.grid_adam.lr * lr_factor;
    // A row's own step counter never exceeds the global one.
    if (im.grid_correction.empty()) im.grid_correction.push_back(0.0);
    while (im.grid_correction.size() <= step_)
        im.grid_correction.push_back(
            adam_bias_correction(cfg_.grid_adam, std::uint32_t(im.grid_correction.size())));
    std::vector<float> grid_max(threads_, 0.0f);
    parallel(threads_, [&](std::uint32_t t) {
        for (std::uint32_t l = 0; l < L; ++l) {
            // The rows this thread scattered into: still in its cache.
            const auto [rb, re] = im.owned[t][l];
            const SparseRows r{grid_[l].data(),
                               im.gm[l].data(),
                               im.gv[l].data(),
                               im.gsum[l].data(),
                               im.active[l].data(),
                               im.row_step[l].data(),
                               F};
            grid_max[t] = std::max(
                grid_max[t],
                adam_update_rows(r, rb, re, grid_lr, im.grid_correction.data(), scale, cfg_.grid_adam));
        }
    });
    // fp16 export needs |p| <= 65504; anything near that is divergence, not learning.
    float maxabs = 0;
    for (const auto& w : w_)
        for (float x : w) maxabs = std::max(maxabs, std::fabs(x));
    for (const auto& b : b_)
        for (float x : b) maxabs = std::max(maxabs, std::fabs(x));
    for (const float x : grid_max) maxabs = std::max(maxabs, x);
    if (!(maxabs < kMaxParam)) {
        rollback();
        lr_scale_ *= 0.5f;
        ++rollbacks_;
        return NAN;
    }
    return loss;
}

void PreparedSet::reserve(std::size_t n, std::uint32_t h) {
    samples.reserve(n);
    count.reserve(n);
    t_near.reserve(n);
    t_far.reserve(n);
    t_first.reserve(n);
    g.reserve(n * h * 3);
}

void PreparedSet::drop_front(std::size_t n) {
    n = std::min(n, samples.size());
    const auto d = std::ptrdiff_t(n);
    samples.erase(samples.begin(), samples.begin() + d);
    count.erase(count.begin(), count.begin() + d);
    t_near.erase(t_near.begin(), t_near.begin() + d);
    t_far.erase(t_far.begin(), t_far.begin() + d);
    t_first.erase(t_first.begin(), t_first.begin() + d);
    g.erase(g.begin(), g.begin() + d * std::ptrdiff_t(H) * 3);
}

TrainResult Trainer::train(const PreparedSet& samples, const ProgressFn& progress, std::uint32_t until_step) {
    const std::uint32_t stop = until_step ? std::min(until_step, cfg_.steps) : cfg_.steps;
    TrainResult res;
    if (samples.size() == 0) {
        res.message = "no training samples reach the network";
        return res;
    }
    const auto t0 = std::chrono::steady_clock::now();
    std::vector<std::uint32_t> batch(cfg_.batch_size);
    // Seeded by the step too, so rounds of train() calls draw fresh batch indices.
    Rng rng{(cfg_.seed ^ 0xA0761D6478BD642Full) + step_ * base::kGoldenGamma};
    std::vector<float> losses;
    while (step_ < stop) {
        for (auto& s : batch) s = std::uint32_t(rng.next() % samples.size());
        const float loss = step(samples, batch);
        res.samples += batch.size();
        if (std::isnan(loss)) {
            if (rollbacks_ > cfg_.max_rollbacks) {
                res.diverged = true;
                res.message = "training diverged: " + std::to_string(rollbacks_) +
                              " rollbacks; kept the last good parameters";
                break;
            }
            continue;
        }
        losses.push_back(loss);
        if (progress) {
            const double secs = base::seconds_since(t0);
            if (!progress({std::uint32_t(step_), cfg_.steps, loss, lr_scale_ * schedule(step_), secs})) {
                res.stopped = true;
                break;
            }
        }
    }
    res.steps = std::uint32_t(step_);
    res.rollbacks = rollbacks_;
    res.seconds = base::seconds_since(t0);
    const std::size_t tail = std::max<std::size_t>(1, losses.size() / 20);
    double sum = 0;
    for (std::size_t i = losses.size() - std::min(tail, losses.size()); i < losses.size(); ++i)
        sum += losses[i];
    res.final_loss = losses.empty() ? NAN : float(sum / double(std::min(tail, losses.size())));
    return res;
}

format::ModelData Trainer::export_model(const std::string& metadata_json) const {
    format::ModelData m = format::make_empty_model(desc_).value();
    m.metadata_json = metadata_json;
    m.occupancy = occupancy_;
    for (std::size_t l = 0; l < grid_.size(); ++l)
        for (std::size_t i = 0; i < grid_[l].size(); ++i) m.grid[l][i] = format::float_to_half(grid_[l][i]);
    for (std::size_t k = 0; k < w_.size(); ++k) {
        for (std::size_t i = 0; i < w_[k].size(); ++i) m.weights[k][i] = format::float_to_half(w_[k][i]);
        for (std::size_t i = 0; i < b_[k].size(); ++i) m.biases[k][i] = format::float_to_half(b_[k][i]);
    }
    return m;
}

void Trainer::round_to_fp16() {
    auto r = [](std::vector<std::vector<float>>& a) {
        for (auto& v : a)
            for (float& x : v) x = format::half_to_float(format::float_to_half(x));
    };
    r(grid_);
    r(w_);
    r(b_);
}

}  // namespace lsnif::trainer
