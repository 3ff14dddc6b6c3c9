// The LSNIF forward pass (docs/architecture.md §3, FORMAT.md §8): ray clipping, voxel DDA over the
// occupancy grid, multi-level hash-grid encoding of the voxel entry points, MLP, decode.
//
// This is THE implementation: the C reader API, the trainer and every benchmark call these
// functions, so what is measured is what a renderer gets. Everything is parametric in the
// descriptor (V, H, levels, T, F, widths); nothing assumes the v1 defaults.
//
// Units: rays are in object space; t is the ray parameter (distance = t * |dir|). Grid
// coordinates g map the box to [0, V]^3: g = (x - box_min) / cell.
#pragma once

#include <lsnif/format/bf16.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/int8.hpp>

#include <algorithm>
#include <array>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace lsnif::format {

// Same layout as lsnif_ray / lsnif_hit of the C API (checked by static_assert).
struct Ray {
    float org[3];
    float tmin;
    float dir[3];
    float tmax;
};

struct Hit {
    float t;                 // ray parameter of the hit (object space t == world t under affine maps)
    float normal[3];         // unit shading normal, object space (world space for instance queries)
    std::uint32_t hit;       // 1 hit, 0 miss
    std::uint32_t material;  // argmax of material logits; 0 when the model has none
};

struct LevelInfo {
    std::uint32_t res;
    bool dense;
    std::uint32_t stride;  // res + 1 (dense indexing)
    std::uint32_t mask;    // T - 1 (hashed indexing; T is a power of two)
    float scale;           // res / V: grid coordinate -> level lattice coordinate
    bool aligned;          // res is a multiple of V: voxel faces lie on lattice planes
};

// Everything the forward pass derives from a descriptor, computed once per model.
struct Geometry {
    std::uint32_t V, H, L, F;
    float box_min[3], box_max[3];
    float diagonal;  // |box_max - box_min|
    std::array<std::uint32_t, 3> primes;
    std::vector<LevelInfo> levels;
    std::uint32_t distance_encoding;
    // MLP input: point_width = H * L * F point features, then direction_width (0 or 3),
    // then offset_width (0 or H) values (FORMAT.md §8).
    std::uint32_t point_width, direction_width, offset_width;
    float cell[3];  // voxel edge per axis, (box_max - box_min) / V in f32 (entry offsets)
    std::uint32_t input_width, output_count, material_count;
};
Geometry make_geometry(const ModelDesc& desc);

// ---- ray -> voxel entry points ------------------------------------------------------

// Points where a ray enters the first H occupied voxels it crosses, in order.
// Definition (exact, what the brute-force test checks): along the clipped segment
// [t_near, t_far] every t lies in exactly one voxel, using cells that are half-open in
// the ray's direction on each axis (closed at the far box face); a voxel is crossed iff
// that set of t is non-empty, and its entry is the smallest such t. Because occupancy is
// conservative with closed voxels, any surface point on the segment lies in an occupied
// crossed voxel, so no true hit is culled.
struct RayPoints {
    std::uint32_t count = 0;  // occupied voxels found (<= H)
    float t_near = 0, t_far = 0;
    float t[kMaxPoints];  // entry parameter per slot
    // Entry point in grid coordinates [0, V]. Coordinates on the voxel face the ray
    // enters through are snapped to that plane exactly (an integer), which is what makes
    // aligned levels touch 4 corners instead of 8.
    float g[kMaxPoints][3];
    std::uint32_t voxel[kMaxPoints];  // linear voxel index x + V*(y + V*z)
    // The ray direction divided by its length (unit_direction), object space: the
    // direction input of models that have one (FORMAT.md §8). Set for every ray whose
    // status is not invalid.
    float dir[3];
};

// enclosed: the walk stopped in an enclosed voxel (OccupancyGrid::enclosed) after an occupied
// one; only where the caller asked for it (stop_at_enclosed), and the points are those
// recorded before it (at least one).
enum class TraceStatus { ok, miss, invalid, enclosed };

// Plane parameter helper shared by the DDA and its reference test, so both compare
// bit-identical values: t at which the ray reaches grid plane `k` on `axis`.
struct RayGrid {
    float go[3];      // origin in grid coordinates
    float gd[3];      // direction in grid units per t
    float inv_gd[3];  // 1 / gd (inf when gd == 0)
    float plane_t(int axis, float k) const { return (k - go[axis]) * inv_gd[axis]; }
};
// Returns invalid for a ray FORMAT.md §8.2 calls invalid: a non-finite origin or direction,
// a NaN bound, a direction that cannot be normalized (normalizable), one that moves
// along no axis of the grid once mapped to grid units, or one with a grid-space component
// whose reciprocal overflows; miss when the ray does not meet the
// box within [tmin, tmax] (also for tmin > tmax).
TraceStatus make_ray_grid(const Geometry& geo, const Ray& ray, RayGrid& rg, float& t_near, float& t_far);

// fma(z, z, fma(y, y, x * x)) of a direction: its squared length as FORMAT.md §8 defines
// it, explicit fused multiply-adds so every build rounds it the same way.
float squared_length(const float d[3]);
// Whether a finite direction's squared_length is positive and finite: a valid ray's
// direction, one that unit_direction maps to a unit vector.
bool normalizable(const float d[3]);

// ray.dir / |ray.dir| as FORMAT.md §8 defines it (the square root of squared_length); the
// network was trained on these bits. `ray.dir` must be normalizable (a valid ray).
void unit_direction(const Ray& ray, float out[3]);

// The entry-offset inputs (FORMAT.md §8): for slot k < pts.count, the distance from entry
// point 0 to entry point k in object space over the box diagonal, from the points' grid
// coordinates (what training and inference both have, bit for bit) with explicit FMAs;
// 0 for empty slots. Writes geo.H values.
void entry_offsets(const Geometry& geo, const RayPoints& pts, float* out);

// The occupancy for inference: per kSubBlock^3 block of voxels, its voxels and whether its
// kBlock^3 and kSuperBlock^3 blocks have an occupied voxel, what lets the DDA jump over
// empty space. It holds the voxels once (the file's OCCU bit array is not kept;
// voxel_bits() rebuilds it): 2 bits per voxel in all.
struct OccupancyGrid {
    static constexpr std::uint32_t kBlock = 4;
    static constexpr std::uint32_t kSubBlock = 2;    // the 16-lane walk's finer empty blocks
    static constexpr std::uint32_t kSuperBlock = 8;  // and its coarser ones
    static constexpr std::uint32_t kBlockBit = 8, kSuperBlockBit = 9;  // bits of a `blocks` entry
    static constexpr std::uint32_t kEnclosedBit = 10;
    std::uint32_t V = 0;
    std::uint32_t S = 0;  // kSubBlock^3 blocks per axis: ceil(V / 2)
    // One entry per kSubBlock^3 block, x fastest (sub_block()), then a zero entry so that
    // any entry can be read as the low half of 32 bits (the 16-lane walk gathers one per
    // step): bits 0-7 the block's voxels (sub_voxel()), bit kBlockBit its kBlock^3 block has
    // an occupied voxel, bit kSuperBlockBit its kSuperBlock^3 block does, bit kEnclosedBit
    // (set by mark_enclosed only) the block has an empty voxel and each of its empty voxels is
    // enclosed (enclosed_voxels()).
    std::vector<std::uint16_t> blocks;
    OccupancyGrid() = default;
    // From an OCCU bit array of a V^3 grid (FORMAT.md §6.3).
    OccupancyGrid(std::uint32_t V, const std::vector<std::uint8_t>& bits);
    std::uint32_t sub_block(std::uint32_t x, std::uint32_t y, std::uint32_t z) const {
        return (x >> 1) + S * ((y >> 1) + S * (z >> 1));
    }
    static std::uint32_t sub_voxel(std::uint32_t x, std::uint32_t y, std::uint32_t z) {
        return (x & 1u) + 2u * (y & 1u) + 4u * (z & 1u);
    }
    bool occupied(std::uint32_t x, std::uint32_t y, std::uint32_t z) const {
        return (blocks[sub_block(x, y, z)] >> sub_voxel(x, y, z)) & 1u;
    }
    bool block_occupied(std::uint32_t x, std::uint32_t y, std::uint32_t z) const {
        return (blocks[sub_block(x, y, z)] >> kBlockBit) & 1u;
    }
    // An empty voxel whose kSubBlock^3 block has kEnclosedBit: what the enclosed rule stops
    // at. Every voxel of an empty aligned block shares a face-connected component, so a walk
    // that skips the block reads its answer at the cell it enters by.
    bool enclosed(std::uint32_t x, std::uint32_t y, std::uint32_t z) const {
        const std::uint16_t e = blocks[sub_block(x, y, z)];
        return ((e >> kEnclosedBit) & 1u) && !((e >> sub_voxel(x, y, z)) & 1u);
    }
    // Sets kEnclosedBit from enclosed_voxels() (on) or clears it (off). Allocates V^3 / 8
    // bytes for the duration of the call (may throw std::bad_alloc).
    void mark_enclosed(bool on);
    // The OCCU bit array this grid was made from, and its number of set bits.
    std::vector<std::uint8_t> voxel_bits() const;
    std::uint64_t occupied_voxels() const;
};

// Fills `out` with up to geo.H occupied entry points. `occupancy` is the OCCU bit array.
// The OccupancyGrid overload skips empty blocks and returns exactly the same points.
TraceStatus trace_points(const Geometry& geo, const std::uint8_t* occupancy, const Ray& ray, RayPoints& out);
// With stop_at_enclosed (the enclosed rule of occlusion queries, docs/model.md): a walk
// that crosses a voxel OccupancyGrid::enclosed() reports after it has recorded a point stops
// there with TraceStatus::enclosed, unless it crossed one before its first occupied voxel
// (it started inside).
TraceStatus trace_points(const Geometry& geo, const OccupancyGrid& occupancy, const Ray& ray, RayPoints& out,
                         bool stop_at_enclosed = false);

// trace_points(geo, occ, rays[i], out[i], stop_at_enclosed) for every i, with status[i] its
// return value: bit-identical results, computed 16 rays at a time with AVX-512 where the CPU
// has it (cpu_features().avx512; the vector corner computation of level_corners needs the
// same). out and status hold rays.size() elements.
void trace_points_batch(const Geometry& geo, const OccupancyGrid& occ, std::span<const Ray> rays,
                        RayPoints* out, TraceStatus* status, bool stop_at_enclosed = false);

// Every voxel crossed (occupied or not), in order, with entry t: for tests and tools.
TraceStatus trace_all_voxels(const Geometry& geo, const Ray& ray, std::vector<std::uint32_t>& voxels,
                             std::vector<float>& entry_t);

// ---- encoding -------------------------------------------------------------------------

// Lattice corners with non-zero trilinear weight around a point of level `lv`. A point on
// a voxel face of an aligned level has one coordinate on a lattice plane, so only 4
// corners carry weight ("sparse" grid, docs/architecture.md §3); the zero-weight ones are dropped.
struct Corners {
    std::uint32_t n;
    std::uint32_t index[8];  // row in the level's table
    float weight[8];
};
void level_corners(const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out);
// The portable scalar level_corners, which the AVX-512 one must match bit for bit (tests).
void level_corners_reference(const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out);

// level_corners of up to 16 points at once: point j < count (at most 16) is (x[j], y[j],
// z[j]); its corners are index[s][j] and weight[s][j] for s < n[j], in level_corners' order
// and bit for bit its values; n[j] = 0 for j >= count, and entries past a point's n are
// unspecified. 16 AVX-512 lanes where the CPU has it (the trainer's gradient scatter calls
// it once per 16 points instead of level_corners per point), else level_corners per point.
struct Corners16 {
    alignas(64) std::uint32_t index[8][16];
    alignas(64) float weight[8][16];
    alignas(64) std::uint32_t n[16];
};
void level_corners16(const Geometry& geo, const LevelInfo& lv, const float* x, const float* y, const float* z,
                     std::uint32_t count, Corners16& out);

// Element type of a GridView.
enum class GridElement : std::uint8_t {
    f32,  // float: the trainer's master copy
    f16,  // IEEE binary16 bit patterns: the reader's runtime for fp16 grids
    u8    // bytes q, value dequantize_u8(q, scale, offset) (FORMAT.md §6.4.1)
};

// One level's feature table as the encoder reads it: entry e's F features start at
// element e * stride. fp16 tables (the reader's runtime: half the memory, so both v1
// levels stay in L2), u8 tables (a quarter) and fp32 tables (the trainer's master copy)
// give identical results for identical values: fp16 -> fp32 is exact, the u8 value is
// one correctly rounded fma, and the interpolation arithmetic is fp32 in all three.
// fp16 and u8 tables must stay readable for 4 elements from the start of every entry
// (grid_tail_pad(F) elements after the last one): the 16-lane encoder reads
// an entry's features with dword gathers and ignores what lies past F.
struct GridView {
    const void* data;
    std::uint32_t stride;  // elements per entry (>= F)
    GridElement element;
    float scale = 0.0f;   // u8 only: the level's dequantization pair
    float offset = 0.0f;  // u8 only
};
// Zero elements a Runtime keeps after an fp16 or u8 table of F features per entry, so
// that the last entry can be read as 4 elements (GridView).
constexpr std::uint32_t grid_tail_pad(std::uint32_t F) {
    return F < 4 ? 4 - F : 0;
}

// Encodes one ray into `row` (input_width floats): the points' features slot-major, then
// level, then feature, empty slots zero; then the ray inputs the model has: pts.dir, and
// entry_offsets().
void encode_points(const Geometry& geo, const GridView* grid, const RayPoints& pts, float* row);
// encode_points(geo, grid, pts[which[j]], rows + j * geo.input_width) for every j, bit for
// bit, computed level by level for 16 points at a time with AVX-512 where the CPU has it
// (F <= 4; otherwise one ray at a time). Rows must not overlap; any number of threads may call it on their
// own rows.
void encode_batch(const Geometry& geo, const GridView* grid, const RayPoints* pts,
                  std::span<const std::uint32_t> which, float* rows);

// ---- MLP --------------------------------------------------------------------------------

// Network in the kernels' layout: per layer W^T [in][out_padded] and bias [out_padded] in
// fp32, out_padded a multiple of 16 (padding columns are zero). Two kinds, by where the
// weights come from:
// - from fp32 arrays (the trainer's master weights): `wt` holds every layer's fp32 W^T and
//   `wt_f16` is empty;
// - from a model (fp16 weights): `wt_f16` holds every layer's W^T in fp16, exactly the
//   model's values, and `wt` only the output layer's (the hidden layers' fp32 entries are
//   empty). The fp32 arithmetic widens the fp16 weights as it loads them (the same bits as
//   fp32 storage), so a model's network holds its weights once, at 2 bytes each, and
//   model_layer_weights() gives the file's arrays back.
struct Network {
    std::vector<std::uint32_t> in, out, out_padded;
    std::vector<std::vector<float>> wt;
    std::vector<std::vector<std::uint16_t>> wt_f16;
    std::vector<std::vector<float>> bias;
    std::size_t max_width_padded = 0;
    // MlpArithmetic::bf16 only (empty otherwise): each hidden layer's W^T as the B operand
    // of gemm_bf16_dp (VNNI layout, K = in padded to 32, N = out_padded).
    std::vector<std::vector<Bf16>> wt_vnni;
    // MlpArithmetic::int8 only (empty otherwise): each hidden layer's weights for gemm_int8,
    // the first layer's with signed inputs.
    std::vector<Int8Layer> wt_int8;
    std::size_t layer_count() const { return in.size(); }
};
// From the fp16 arrays of a model (weights [out][in] row-major).
Network make_network(const ModelData& model);
// From fp32 arrays in file layout (trainer master weights).
Network make_network(const ModelDesc& desc, const std::vector<std::vector<float>>& weights,
                     const std::vector<std::vector<float>>& biases);
// A model network's layer k in the file's layout (FORMAT.md §6.5): weights fp16 [out][in]
// row-major and bias fp16 [out], the exact values make_network(ModelData) read. Requires a
// network made from a model (wt_f16 not empty).
std::vector<std::uint16_t> model_layer_weights(const Network& net, std::size_t k);
std::vector<std::uint16_t> model_layer_bias(const Network& net, std::size_t k);

// Hidden layer k (k + 1 < layer_count()) in fp32 arithmetic with ReLU, from whichever
// storage the network has (fp32 or fp16 W^T; the same bits): C [n][out_padded[k]] from A
// (row stride lda). `zeros` as for dense_layer_strided.
void hidden_layer_fp32(const Network& net, std::size_t k, const float* A, std::size_t n, std::size_t lda,
                       float* C, const ZeroColumns* zeros = nullptr);

// C[n][0..out_padded) = act(A[n][0..in) · Wt + bias). A has row stride `lda`, C has row
// stride out_padded. ReLU when `relu`. Vectorized for AVX-512/AVX2 with runtime dispatch;
// every variant computes each output as its bias, then one fused multiply-add per input in
// input order, so all give the same bits.
void dense_layer(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                 const float* bias, std::size_t out_padded, bool relu, float* C);
// dense_layer on the first `out` columns (a multiple of 16) of weights with row stride `ldw`
// (Wt[i][o] at wt[i * ldw + o]; bias readable for `out` values) into C with row stride
// `ldc`. With `relu`, inputs that `zeros` names as zero (true of A) are skipped per block of
// rows: the same results bit for bit (a skipped term only changes the sign of a zero sum,
// which ReLU maps to +0); without `relu`, `zeros` is ignored.
void dense_layer_strided(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                         std::size_t ldw, const float* bias, std::size_t out, bool relu, float* C,
                         std::size_t ldc, const ZeroColumns* zeros);
// The same with fp16 weights, widened exactly on load (the same bits as their fp32 values).
void dense_layer_strided(const float* A, std::size_t n, std::size_t in, std::size_t lda,
                         const std::uint16_t* wt, std::size_t ldw, const float* bias, std::size_t out,
                         bool relu, float* C, std::size_t ldc, const ZeroColumns* zeros);

// The output layer: dense_layer without ReLU, whose first `outs` columns it equals bit for
// bit; the padding columns [outs, out_padded) hold zeros or dense_layer's values (both are
// never read). Faster for out_padded == 16 (rows in vector lanes, only real outputs computed).
void dense_output_layer(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                        const float* bias, std::size_t out_padded, std::size_t outs, float* C);

// Arithmetic of the hidden layers' products. fp32 is FORMAT.md §8's reference. bf16 rounds
// each hidden layer's input and weights to bfloat16 and accumulates in fp32 (AVX-512 BF16).
// int8 quantizes each hidden layer's input per row and its weights per output column to 8
// bits and sums the products exactly in int32 (AVX-512 VNNI, lsnif/format/int8.hpp). In
// both, bias, ReLU and the output layer stay fp32 (the visibility logit and the distance are
// read from the output layer directly, so its inputs keep full precision). Hit decisions
// agree with fp32 on >= 99.5 % of rays and the held-out metrics move by <= 0.1 point
// (tests/convert/test_accuracy.cpp, on the shipped assets).
enum class MlpArithmetic : std::uint8_t { fp32, bf16, int8 };
// The fastest the CPU runs: int8 with AVX-512 VNNI, else bf16 with AVX-512 BF16, else fp32.
MlpArithmetic best_mlp_arithmetic();
// Sets the arithmetic of a network: packs wt_vnni or wt_int8 from the hidden layers' fp32
// or fp16 W^T and then releases the hidden layers' fp32 W^T, which the reduced arithmetics
// never read (the output layer's stays; a model network's fp16 W^T stays too, as the
// weights of record). A model network can go from any arithmetic to any other; a network
// from fp32 arrays that is already reduced keeps its arithmetic (make a new one to change
// it). What the CPU lacks falls back: int8 to bf16 (also for a layer wider than
// kInt8MaxInputs), bf16 to fp32. Returns the arithmetic now in use.
MlpArithmetic set_mlp_arithmetic(Network& net, MlpArithmetic a);
MlpArithmetic mlp_arithmetic(const Network& net);

// Runs all layers in the network's arithmetic. `scratch` grows as needed; the result is n
// rows of net.out_padded.back() floats, returned as a pointer into scratch. `input_zeros`,
// if given, says which inputs are zero (e.g. the empty point slots, lead = count * L * F,
// tail = point_width, and their entry offsets, rest = count from the offsets' first column);
// the bf16 and int8 first layers skip them (same results). `outputs`
// > 0: the caller reads only the first `outputs` columns of each result row (the others are
// unspecified); 0 = all.
const float* mlp_forward(const Network& net, const float* input, std::size_t n, std::vector<float>& scratch,
                         const ZeroColumns* input_zeros = nullptr, std::size_t outputs = 0);

// ---- decode -------------------------------------------------------------------------------

// Turns one output row (OutputLayout) into a hit (FORMAT.md §8): hit iff logit > 0; t from
// the distance encoding, clamped to the clipped segment; normal normalized (−dir if
// degenerate).
Hit decode_output(const Geometry& geo, const RayPoints& pts, const Ray& ray, const float* out_row);
// decode_output's hit decision alone: the ray crossed an occupied voxel and the visibility
// logit is positive. The any-hit query (occluded) reads nothing else.
inline bool hit_decision(const RayPoints& pts, const float* out_row) {
    return pts.count > 0 && out_row[OutputLayout::visibility] > 0.0f;
}

// The distance encoding of FORMAT.md §6.2 both ways. `t` is the ray parameter, `y` the
// network's distance output, `dir_length` = |ray.dir|; `pts` is the ray's trace (count > 0).
// encode_distance is decode_distance's inverse before decode's clamp to the segment: the
// trainer's distance target.
inline float decode_distance(const Geometry& geo, const RayPoints& pts, float dir_length, float y) {
    return geo.distance_encoding == LSNIF_DISTANCE_SEGMENT ? pts.t_near + y * (pts.t_far - pts.t_near)
                                                           : pts.t[0] + y * geo.diagonal / dir_length;
}
inline float encode_distance(const Geometry& geo, const RayPoints& pts, float dir_length, float t) {
    return geo.distance_encoding == LSNIF_DISTANCE_SEGMENT
               ? (t - pts.t_near) / std::max(pts.t_far - pts.t_near, 1e-30f)
               : (t - pts.t[0]) * dir_length / geo.diagonal;
}

// ---- the whole pass ------------------------------------------------------------------------

// Decoded, inference-ready model: feature tables in their stored precision and layout (fp16
// or u8, dequantized on the gather), the occupancy grid and the network (Network: its fp16
// weights, widened on load by the fp32 arithmetic). Immutable once built, so any number of
// threads may call intersect() on it concurrently.
struct Runtime {
    Geometry geo;
    OccupancyGrid occupancy;
    // Per level, the file's GRID array (entries * F elements, FORMAT.md §6.4) followed by
    // grid_tail_pad(F) zeros; only the one desc.grid_encoding names is filled.
    std::vector<std::vector<std::uint16_t>> grid;    // fp16 grids
    std::vector<std::vector<std::uint8_t>> grid_u8;  // u8_affine grids
    std::vector<LevelAffine> grid_affine;            // u8_affine grids: per level
    Network net;
    // The escape rule (lsnif_set_escape_points): a ray whose segment starts inside an
    // occupied voxel and meets at most this many occupied voxels, that one included, is a
    // miss without the network. 0 turns it off (FORMAT.md §8 as written). Set it as the
    // network's arithmetic: not while other threads trace through the runtime.
    std::uint32_t escape_points = 0;
    // The enclosed rule (lsnif_set_enclosed_rule): while it is on, occupancy's kEnclosedBit
    // is marked (OccupancyGrid::mark_enclosed) and occluded() answers a ray whose walk stops
    // in an enclosed voxel (TraceStatus::enclosed) as occluded. Change it with
    // set_enclosed_rule(), which keeps the two together, as escape_points.
    bool enclosed_rule = false;
    std::vector<GridView> grid_views() const;
    // Heap bytes this runtime holds (every array's capacity): what it costs a renderer
    // beyond sizeof(Runtime). Depends on the network's arithmetic (set_mlp_arithmetic).
    std::uint64_t heap_bytes() const;
};
// The network starts in `arithmetic` (set_mlp_arithmetic(rt.net, ...) changes it later;
// not while other threads call intersect on the runtime). The rvalue overload takes the
// occupancy, the feature tables, the weights and the biases out of `model` (leaving them
// empty), so the model's arrays are held once: by the runtime, in its own layouts
// (OccupancyGrid::voxel_bits, model_layer_weights and model_layer_bias give the file's
// arrays back).
Runtime make_runtime(const ModelData& model, MlpArithmetic arithmetic = MlpArithmetic::fp32);
Runtime make_runtime(ModelData&& model, MlpArithmetic arithmetic = MlpArithmetic::fp32);

// The resident bytes of `model` once opened through the C API with the fp32 network (the
// reference arithmetic, which every CPU runs and which holds the least:
// lsnif_info::decoded_bytes after lsnif_set_arithmetic(LSNIF_ARITHMETIC_FP32), before any
// lsnif_get_array). Deterministic: a function of the model alone.
std::uint64_t resident_bytes(const ModelData& model);

// Statistics of one batch, for benchmarks and evaluation.
struct IntersectStats {
    // escaped: rays the escape rule (Runtime::escape_points) answered without the network;
    // enclosed: rays the enclosed rule (Runtime::enclosed_rule) answered occluded without it.
    std::size_t rays = 0, invalid = 0, culled = 0, escaped = 0, enclosed = 0, inferred = 0, hits = 0;
};

// Whether voxels `a` and `b` (linear indices x + V * (y + V * z) of a V^3 grid) share a
// face: they differ by one along exactly one axis. Called per point of every ray the escape
// rule looks at (escapes()): for a power-of-two V (every preset's grid) the coordinates come
// from shifts and masks instead of divisions by a V known only at run time.
inline bool face_neighbours(std::uint32_t a, std::uint32_t b, std::uint32_t V) {
    const auto apart = [](std::uint32_t u, std::uint32_t v) { return u > v ? u - v : v - u; };
    if (std::has_single_bit(V)) {
        const int s = std::countr_zero(V);
        const std::uint32_t m = V - 1;
        return apart(a & m, b & m) + apart((a >> s) & m, (b >> s) & m) + apart(a >> 2 * s, b >> 2 * s) == 1;
    }
    const std::uint32_t ax = a % V, ay = a / V % V, az = a / V / V;
    const std::uint32_t bx = b % V, by = b / V % V, bz = b / V / V;
    return apart(ax, bx) + apart(ay, by) + apart(az, bz) == 1;
}

// Whether the escape rule with limit `escape_points` answers `ray` (traced into `pts` on
// the grid of `geo`) as a miss: its segment starts inside the first occupied voxel it meets
// (that voxel's entry is the ray's own tmin, so a ray entering the grid from outside never
// escapes), it meets at most `escape_points` occupied voxels, and each of them shares a face
// with the one before it: one run of occupied voxels from the start, the shell of the
// surface the ray leaves, with no empty voxel between (a ray that crosses empty space and
// meets occupied voxels again approaches another surface and goes to the network).
// Always false for escape_points = 0.
inline bool escapes(const Geometry& geo, const RayPoints& pts, const Ray& ray, std::uint32_t escape_points) {
    if (pts.count == 0 || pts.count > escape_points || !(pts.t[0] <= ray.tmin)) return false;
    for (std::uint32_t k = 1; k < pts.count; ++k)
        if (!face_neighbours(pts.voxel[k - 1], pts.voxel[k], geo.V)) return false;
    return true;
}

// The empty voxels of `occ` that no path of empty face neighbours joins to the grid's
// boundary: the space a closed shell of occupied voxels shuts in, the inside of a closed
// surface. One bit per voxel, bit i of word i / 64 for voxel i = x + V * (y + V * z).
std::vector<std::uint64_t> enclosed_voxels(const OccupancyGrid& occ);

// Turns the enclosed rule of `rt` on or off: the occupancy's marks and Runtime::enclosed_rule
// together. May throw std::bad_alloc (OccupancyGrid::mark_enclosed); the rule is then off.
void set_enclosed_rule(Runtime& rt, bool on);

// Bit `voxel` of a bit array laid out as enclosed_voxels() returns it.
inline bool voxel_bit(const std::uint64_t* bits, std::uint32_t voxel) {
    return (bits[voxel >> 6] >> (voxel & 63u)) & 1u;
}
inline void set_voxel_bit(std::uint64_t* bits, std::uint32_t voxel) {
    bits[voxel >> 6] |= std::uint64_t(1) << (voxel & 63u);
}

// Object-space batch. Single-threaded: callers parallelize across batches (renderers
// bring their own thread pools). Invalid rays (zero direction...) report a miss.
IntersectStats intersect(const Runtime& rt, std::span<const Ray> rays, std::span<Hit> hits);
// The any-hit query of the same batch: occluded[i] = hits[i].hit of intersect(), computed
// without the hit's distance, normal and material (only the visibility output). Same
// threading rules. Both apply the runtime's escape rule; occluded() also its enclosed rule,
// first (a ray both would take is occluded).
IntersectStats occluded(const Runtime& rt, std::span<const Ray> rays, std::span<std::uint8_t> occluded);

}  // namespace lsnif::format
