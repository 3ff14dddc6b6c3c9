// Training of one LSNIF (docs/architecture.md §3): losses, backward pass through the MLP and the
// sparse hash-grid encoding, hand-written Adam, learning-rate schedule, gradient clipping
// and a divergence guard. Multi-threaded on the shared pool (lsnif/base/parallel.hpp); for a
// fixed seed every step gives the same bits for any thread count: a batch is cut into chunks
// that depend on its size alone, each chunk's gradients are summed over its rows in order and
// the chunks are added in chunk order, and each hash-table row is summed by the one thread
// that owns it, over the batch in order (Adam then updates the rows in place). Threads only
// decide who computes which chunk. With MlpPrecision::fp32 the steps are also the same on
// every CPU (AVX-512, AVX2, the portable paths: fused multiply-adds in one order); bf16 runs
// on AMX or AVX-512 BF16, whose sums the other paths cannot reproduce.
//
// The forward computation is format/'s (trace_points, encode_points, dense_layer), so a
// model trained here evaluates identically in a renderer once exported to fp16
// (predict_raw checks this). Training steps may run the MLP products in bf16 on Intel AMX
// instead (TrainConfig::mlp_precision); that changes the arithmetic of training, not of
// prediction, export or evaluation.
#pragma once

#include <lsnif/base/huge_pages.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/samples/sample.hpp>
#include <lsnif/trainer/adam.hpp>

#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

namespace lsnif::trainer {

// The trainer consumes ground-truth rays of lsnif::samples (sample.hpp); these are the
// names its interface uses for them.
using samples::Family;
using samples::Sample;
using samples::SampleSource;

// Loss weights, dimensionless multipliers of each term's mean. Distance weighs most because,
// at equal steps, a heavier distance term lowers the distance and normal errors without
// costing visibility (docs/investigations/losses.md "The loss weights"); the converter's
// presets set their own (docs/model.md "Outputs and losses").
struct LossWeights {
    float visibility = 1.0f;
    float distance = 4.0f;
    float normal = 1.0f;
    float material = 0.1f;
};

// Shape of the normal loss, a function of the angle θ between the predicted direction (the
// raw output, normalized) and the unit target normal:
//   cosine: 1 - cos θ ≈ θ²/2, a squared error on unit vectors. Its gradient fades as θ -> 0,
//           so the large errors of a batch decide most of a step.
//   chord:  sqrt(2 (1 - cos θ) + ε²) - ε, the chord |n̂ - n| = 2 sin(θ/2) ≈ θ smoothed below
//           ε: an absolute error, whose gradient keeps its size down to θ ≈ ε, so the typical
//           hit pulls as hard as the outliers. The metric users read is the median angle;
//           on CGAL's dragon and armadillo this shape lowers it by 1-2 degrees at equal
//           visibility and steps (docs/model.md "The normal loss").
// Both shapes see only the direction of the output, so their gradient vanishes where it
// points exactly away from the target; either is summed with the hinge max(0, -n·t) on the
// raw output n (smoothed below 0.05), which pulls a wrong-hemisphere prediction toward the
// target through the origin and is zero wherever the prediction is in the target's
// hemisphere.
enum class NormalLoss : std::uint8_t { cosine, chord };

// Arithmetic of the MLP matrix products inside training steps (loss_and_gradients: forward
// hidden and output layers, input gradients, weight gradients). bf16 rounds the operands of
// those products to bfloat16 and runs them with fp32 accumulation on Intel AMX tiles, or
// with AVX-512 BF16 dot products (VDPBF16PS) where there is no AMX; bias, activations,
// losses, gradient reductions, master weights and Adam stay fp32. fp32 uses format/'s
// kernels throughout (exact enough for finite-difference checks). automatic = bf16 when
// the CPU and OS provide either (see Trainer::mlp_precision), else fp32.
// predict_raw, export and evaluation are fp32 whatever this says.
enum class MlpPrecision : std::uint8_t { fp32, bf16, automatic };
const char* precision_name(MlpPrecision p);
// What a Trainer built with `requested` will run: bf16 only where the CPU and OS allow AMX
// or AVX-512 BF16. Weights trained in bf16 and fp32 differ, so callers that cache assets
// key on this.
MlpPrecision resolve_precision(MlpPrecision requested);
// The arithmetic `requested` resolves to on this machine, with the instructions that run it:
// "fp32", "bf16/amx" or "bf16/avx512-bf16". The two bf16 kernels sum in different orders,
// so their weights differ in the last bits: asset cache keys use this, not precision_name.
std::string mlp_arithmetic(MlpPrecision requested);

struct TrainConfig {
    std::uint32_t steps = 2000;
    std::uint32_t batch_size = 1u << 14;
    std::uint32_t threads = 0;  // 0 = all hardware threads; never changes a result
    std::uint64_t seed = 1;
    AdamConfig grid_adam{2e-2f, 0.9f, 0.99f, 1e-10f, 0.0f};
    AdamConfig mlp_adam{1e-2f, 0.9f, 0.99f, 1e-10f, 1e-6f};
    // Schedule: constant, then exponential decay from decay_start (fraction of steps)
    // down to final_lr_fraction of the initial rate at the last step.
    float decay_start = 0.4f;
    float final_lr_fraction = 0.05f;
    float huber_delta = 0.01f;  // distance loss: quadratic below this error (diagonal units)
    NormalLoss normal_loss = NormalLoss::cosine;
    float normal_chord_epsilon = 0.01f;  // ε of NormalLoss::chord (in chord length, ~radians)
    float grad_clip_norm = 10.0f;        // global L2 norm of all gradients; <= 0 disables
    LossWeights loss;
    // Divergence guard: a step whose loss is non-finite, or above divergence_factor x the
    // running mean after warm-up, is undone: parameters roll back to the last snapshot
    // and the learning rate is halved. Gives up after max_rollbacks.
    float divergence_factor = 8.0f;
    std::uint32_t snapshot_interval = 50;
    std::uint32_t max_rollbacks = 8;
    // bf16 requested on a machine without AMX falls back to fp32 (never an error).
    MlpPrecision mlp_precision = MlpPrecision::automatic;
};

struct Progress {
    std::uint32_t step, steps;
    float loss;
    float lr_scale;
    double seconds;
};
// Return false to stop training early (the model so far is kept).
using ProgressFn = std::function<bool(const Progress&)>;

struct TrainResult {
    std::uint32_t steps = 0;
    double seconds = 0;
    std::uint64_t samples = 0;
    float final_loss = 0;  // mean loss over the last 5% of steps
    std::uint32_t rollbacks = 0;
    bool diverged = false;  // gave up after max_rollbacks; the last good snapshot is kept
    bool stopped = false;   // the progress callback returned false (at any step, the last included)
    std::string message;
};

// Loss terms of one evaluation (means as used for the gradient).
struct LossParts {
    double total = 0, visibility = 0, distance = 0, normal = 0, material = 0;
};

// Gradients of every parameter, in the layouts of Trainer's accessors.
struct Gradients {
    std::vector<std::vector<float>> grid;     // per level, entries * F
    std::vector<std::vector<float>> weights;  // per layer [out][in]
    std::vector<std::vector<float>> biases;   // per layer [out]
};

// Training samples with their ray features (voxel entry points) computed once: the
// points depend only on the ray and the occupancy, both fixed during training, so the
// DDA runs once per sample instead of once per epoch. Only reachable samples are kept.
//
// Allocator for the set's buffers: resize() leaves new elements default-initialized (no
// zeroing) — every element is written before it is read, so zeroing hundreds of MB per round
// of streamed rays would be pure cost (docs/investigations/conversion-time.md). Large buffers
// go on transparent huge pages (base/huge_pages.hpp): fewer page faults when a round's
// buffers are first filled, fewer TLB misses when steps read them at random.
template <class T>
struct DefaultInitAllocator : std::allocator<T> {
    template <class U>
    struct rebind {
        using other = DefaultInitAllocator<U>;
    };
    DefaultInitAllocator() noexcept = default;
    template <class U>
    DefaultInitAllocator(const DefaultInitAllocator<U>&) noexcept {}
    T* allocate(std::size_t n) { return static_cast<T*>(base::allocate_large(n * sizeof(T))); }
    void deallocate(T* p, std::size_t n) noexcept { base::free_large(p, n * sizeof(T)); }
    template <class U>
    void construct(U* p) noexcept(std::is_nothrow_default_constructible_v<U>) {
        ::new (static_cast<void*>(p)) U;
    }
    template <class U, class... Args>
    void construct(U* p, Args&&... args) {
        ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
    }
};
template <class T>
using Buffer = std::vector<T, DefaultInitAllocator<T>>;

struct PreparedSet {
    Buffer<Sample> samples;
    Buffer<std::uint16_t> count;  // occupied entry points per sample (1..H)
    Buffer<float> t_near, t_far, t_first;
    Buffer<float> g;  // samples x H x 3 grid coordinates (slots past count unused)
    std::uint32_t H = 0;
    std::size_t size() const { return samples.size(); }
    // Streaming training data (rounds of fresh rays, added by Trainer::prepare_append): drops
    // the oldest n samples. Keeps the buffers' capacity, so a window that is refilled every
    // round stops allocating (fresh pages cost a page fault each) once it has reached its
    // largest size.
    void drop_front(std::size_t n);
    // Capacity for n samples of `h` entry points each (no allocation while size() <= n).
    void reserve(std::size_t n, std::uint32_t h);
};

class Trainer {
public:
    // `occupancy` is the OCCU bit array for desc.grid_resolution. Parameters are
    // initialized from cfg.seed: grid U(-1e-4, 1e-4), hidden layers He-uniform, output
    // layer Xavier-uniform, biases zero.
    Trainer(const format::ModelDesc& desc, std::vector<std::uint8_t> occupancy, const TrainConfig& cfg);
    ~Trainer();
    Trainer(const Trainer&) = delete;
    Trainer& operator=(const Trainer&) = delete;

    const format::ModelDesc& desc() const { return desc_; }
    const format::Geometry& geometry() const { return geo_; }
    const std::vector<std::uint8_t>& occupancy() const { return occupancy_; }
    const TrainConfig& config() const { return cfg_; }

    // Keeps only the samples whose ray reaches the network (crosses an occupied voxel).
    std::vector<Sample> reachable(std::span<const Sample> samples) const;

    // Traces every sample once (multi-threaded); drops those that do not reach the network.
    PreparedSet prepare(std::span<const Sample> samples) const;
    // The same appended to `out` (empty, or prepared by this trainer), in sample order, with
    // the trainer's scratch space reused: the form for rounds of streamed rays, which land
    // straight in the window of rounds instead of in a set of their own that is then copied
    // (every buffer a round first touches costs page faults: docs/investigations/conversion-time.md
    // "Huge pages for the prepared rays"). Not thread-safe with itself.
    void prepare_append(std::span<const Sample> samples, PreparedSet& out) const;

    // Trains cfg.steps steps on random batches (with replacement) from `samples`.
    // Deterministic for (seed, samples), whatever the thread count.
    TrainResult train(std::span<const Sample> samples, const ProgressFn& progress = {});
    // Runs steps until step() == until_step (0: cfg.steps); the schedule always spans
    // cfg.steps, so a caller may train in rounds on changing sets. Counters (samples,
    // seconds) are those of this call.
    TrainResult train(const PreparedSet& set, const ProgressFn& progress = {}, std::uint32_t until_step = 0);

    // One optimizer step on the samples `batch` indexes. Returns the batch loss before
    // the update; NaN when the step was rejected by the divergence guard.
    float step(const PreparedSet& set, std::span<const std::uint32_t> batch);
    float step(std::span<const Sample> batch);  // prepares `batch` first (tests)

    // Loss and exact gradients without updating (for gradient checks).
    LossParts loss_and_gradients(const PreparedSet& set, std::span<const std::uint32_t> batch,
                                 Gradients* grads);
    LossParts loss_and_gradients(std::span<const Sample> batch, Gradients* grads);

    // fp16 export (the .lsnif content). Rounds every master weight to nearest-even.
    format::ModelData export_model(const std::string& metadata_json) const;
    // Replaces the master weights by their fp16-rounded values (so training-side and
    // reader-side evaluation see the same numbers).
    void round_to_fp16();

    // Raw outputs (output_count floats per sample, unpadded) of the training-side forward.
    std::vector<float> predict_raw(std::span<const Sample> batch);

    // Master parameters (fp32), file layouts: grid[level][entry*F + f],
    // weights[layer][out*in + i], biases[layer][out].
    std::vector<std::vector<float>>& grid() { return grid_; }
    std::vector<std::vector<float>>& weights() { return w_; }
    std::vector<std::vector<float>>& biases() { return b_; }
    std::uint32_t threads() const { return threads_; }
    // The precision training steps actually use: fp32 or bf16, never automatic.
    MlpPrecision mlp_precision() const { return precision_; }
    std::uint64_t step_count() const { return step_; }
    float lr_scale() const { return lr_scale_; }
    // Multiplies both learning rates (the guard halves it; tests force absurd rates).
    void set_lr_scale(float s) { lr_scale_ = s; }
    std::uint32_t rollbacks() const { return rollbacks_; }

    // FLOPs of the MLP part of one training sample (forward + backward), for benchmarks.
    double mlp_flops_per_sample() const;

private:
    struct Impl;
    Impl* impl_;
    format::ModelDesc desc_;
    format::Geometry geo_;
    std::vector<std::uint8_t> occupancy_;
    TrainConfig cfg_;
    std::uint32_t threads_;
    MlpPrecision precision_ = MlpPrecision::fp32;
    std::vector<std::vector<float>> grid_, w_, b_;
    std::uint64_t step_ = 0;
    float lr_scale_ = 1.0f;
    std::uint32_t rollbacks_ = 0;
    float schedule(std::uint64_t step) const;
    void snapshot();
    void rollback();
    friend struct Impl;
};

}  // namespace lsnif::trainer
