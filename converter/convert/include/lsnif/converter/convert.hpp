// `lsnif convert`: scene import -> classification -> voxelization -> Embree ground truth ->
// training -> held-out evaluation and gate -> .lsnif assets + manifest (docs/architecture.md §1).
//
// Library code: never prints or exits. Progress goes through a callback; problems are
// collected per input and per mesh; the CLI decides what to print and the exit code.
#pragma once

#include <lsnif/converter/outcome.hpp>
#include <lsnif/converter/rules.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::converter {

// A byte count such as "1500000", "512K", "64MiB" or "1.5G" into `bytes` (K, M, G, T are
// powers of 1024; an optional "B" or "iB" after them; case-insensitive). False with a
// one-line `error` for anything else: empty, negative, zero, not a number, trailing text,
// or more than 2^63 bytes.
bool parse_byte_size(const std::string& text, std::uint64_t& bytes, std::string& error);

// Box extents (largest axis of the padded box, in the mesh's units) that LSNIF models in
// single precision: squared distances and dot products of box-sized vectors stay inside
// float's normal range (~1e-38 .. 3e38) with margin. A mesh outside stays BVH, with the
// reason, even when forced with --complex.
inline constexpr double kMinModelExtent = 1e-15;
inline constexpr double kMaxModelExtent = 1e15;

struct Preset {
    std::string name;
    format::ModelDesc model;     // box is filled per mesh
    trainer::TrainConfig train;  // threads/seed are filled from the options
    // Training data is streamed in rounds: round r draws `train_chunk_rays` fresh rays, and
    // steps of that round sample the latest `train_window_chunks` chunks. Distinct rays
    // because a smaller set reused for many epochs is overfitted; rounds because only the
    // window, not every ray, is held in memory (docs/model.md "Training data in rounds").
    std::uint64_t train_rays = 1u << 20;        // distinct training rays in all rounds
    std::uint64_t train_chunk_rays = 1u << 20;  // rays per round
    std::uint32_t train_window_chunks = 2;      // chunks a step samples from
    std::uint64_t eval_rays = 1u << 16;
    // Validation during training (docs/model.md "Validation curve"): `validation_rays` rays of
    // the three families, drawn apart from the training and held-out rays, are measured
    // through the reader's forward pass `validation_checks` times at evenly spaced steps.
    // The curve is recorded in the manifest; the held-out set stays untouched until the gate.
    std::uint64_t validation_rays = 1u << 13;
    std::uint32_t validation_checks = 10;
    // Inactive neurons (docs/model.md "Inactive neurons"): after training, every hidden
    // neuron whose ReLU output is zero on all `validation_rays` is removed with its weights,
    // so the shipped network is only as wide as the object uses (smaller and faster to run).
    bool prune_inactive = true;
    // The visual check (docs/model.md "Judged by how it looks"): every option of the ladder is
    // rendered in these views through its asset and compared with Embree's render by FLIP;
    // off: no views, no FLIP in the manifest.
    bool visual_check = true;
    render::ObjectViewOptions views;
    ClassifyRule classify;
    Gate gate;
    EarlyAbort early_abort;
    TargetStop target_stop;
    Sizing sizing;
};
// "default" (the shipped model: presets.cpp writes it out whole), "fast", "quality" (the same
// model, fewer or more training rays per step and steps) and "smoke" (a tiny model for
// pipeline checks).
bool find_preset(const std::string& name, Preset& out);
std::vector<std::string> preset_names();

// The arithmetic a conversion trains with (docs/pipeline.md "The same bytes everywhere").
//   canonical  fp32 in one fixed order: the same weights, metrics and decisions on every CPU
//              (AVX2, AVX-512, AMX machines, the portable build's scalar paths) and for any
//              thread count. The default.
//   machine    the MLP products of training in bf16 on Intel AMX or AVX-512 BF16 where the
//              CPU has them (fp32 elsewhere, which is the canonical arithmetic): faster on those
//              CPUs, but the weights depend on the CPU kind, so assets, cache keys and
//              manifests name the instructions (arithmetic_id).
enum class Arithmetic : std::uint8_t { canonical, machine };
// The version of the canonical arithmetic: bumped whenever an operation whose result
// reaches an asset or a decision (training, sampling, metrics, pruning, quantization) rounds
// differently. Recorded in assets and manifests; part of every cache key.
inline constexpr int kCanonicalArithmeticVersion = 1;
// What `a` runs as on this machine: "canonical-1", or "machine-bf16/amx" /
// "machine-bf16/avx512-bf16" (machine on a CPU without bf16 products is canonical).
std::string arithmetic_id(Arithmetic a);
// "canonical" or "machine" (the --arithmetic values); false for anything else.
bool parse_arithmetic(const std::string& text, Arithmetic& out);

// The seeds (ObjectViewOptions::seed) of a conversion's two sets of object views: the decision
// views from the run's --seed, the held-out views from --view-seed (the run's seed by
// default), each through its own mix so that the two never share a camera.
std::uint64_t decision_view_seed(std::uint64_t seed);
std::uint64_t held_out_view_seed(std::uint64_t view_seed);

// The reason recorded for a candidate that ConvertOptions::only_keys leaves to another job.
inline constexpr const char* kLeftToAnotherJob = "left to another job (lsnif batch --object)";

struct ConvertOptions {
    std::vector<std::string> inputs;
    std::string outdir;
    std::uint64_t seed = 1;
    // Threads and jobs decide how fast, never what: results are the same for any count.
    std::uint32_t threads = 0;  // 0 = hardware threads
    // --jobs: candidates converted at once, each with threads / jobs threads (at least 1).
    // Cannot be combined with memory_budget, which decides each conversion from the last.
    std::uint32_t jobs = 1;
    Arithmetic arithmetic = Arithmetic::canonical;  // --arithmetic
    std::string preset = "default";
    std::vector<std::string> force_complex;  // mesh names
    std::vector<std::string> force_simple;
    std::string command_line;          // recorded in metadata
    double gate_min_visibility = -1;   // >= 0 overrides the preset's pooled visibility gate
    double gate_max_flip = -1;         // >= 0 overrides the preset's image gate (Gate::max_flip)
    std::optional<Acceptance> accept;  // overrides the preset's Gate::accept
    std::uint32_t steps = 0;           // > 0 overrides the preset's training steps
    std::uint32_t batch_size = 0;      // > 0 overrides the preset's batch size
    // Import and classify only; report the plan (each candidate's cache key and estimated
    // conversion time with it: `cache_key`, `estimated_ms`), write nothing.
    bool dry_run = false;
    // --cache DIR|URL: a content-addressed store (lsnif::cache) of every candidate's result,
    // shared between runs, processes and machines: a directory or an http(s) server; empty =
    // none (docs/pipeline.md). --cache-local: a directory in front of a server.
    // --cache-read-only: never write to the server. --cache-timeout: seconds per request.
    std::string cache;
    std::string cache_local;
    bool cache_read_only = false;
    double cache_timeout = 10;
    // The server's bearer token (LSNIF_CACHE_TOKEN, read by the command line): sent to the
    // server, never recorded, printed or keyed.
    std::string cache_token;
    // --shard I/N (`lsnif batch`): convert only the candidates this shard owns (the candidates
    // of all inputs, costliest first by an estimate of their conversion time, ties by cache
    // key, each dealt to the shard with the least estimated work); the others are recorded as
    // owned by their shard for `lsnif merge`. shard_count 0 = no sharding.
    std::uint32_t shard_index = 0, shard_count = 0;
    // --object KEY (`lsnif batch`; one edge of a Ninja file, docs/pipeline.md "Ninja"):
    // convert only the candidates with these cache keys, into the cache and OUTDIR's assets;
    // the others are left to other jobs and no manifest is written (the library's last step
    // writes it, from the cache). A key no candidate has is an error, and so is a result
    // that could not be stored (the Ninja edge's output is the cache entry).
    std::vector<std::string> only_keys;
    // Also write OUTDIR/scene.gltf (+ scene.bin): the scene with the LSNIF_neural_geometry
    // extension on every converted mesh (gltf_out.hpp). `lsnif batch` converts libraries,
    // not scenes, and leaves it out.
    bool write_gltf = true;
    // Leave run-dependent fields (timings, reused) out of the manifest, so that it is a
    // function of the inputs, the settings and the build alone (`lsnif batch`, `lsnif merge`).
    bool reproducible_manifest = false;
    // Train one model per mesh for the preset's whole budget, as before sizing existed: no
    // smaller rungs, no 8-bit option, no TargetStop (EarlyAbort and the gate still apply).
    bool fixed_model = false;
    // --no-give-up: train to the end of the budget even where the validation curve shows the
    // gate is out of reach (EarlyAbort off), to measure how far hard geometry gets. The gate
    // still decides what ships.
    bool no_give_up = false;
    // --keep-inactive: ship the trained network whole (Preset::prune_inactive off), to
    // measure what pruning changes.
    bool keep_inactive = false;
    Target target;  // --target: judged and reported per shipped asset
    // --view-seed: draws the held-out views a shipped asset's image error is reported on
    // (none = the run's seed). Decisions never see them, so it changes what is reported, not
    // which asset ships or its bytes.
    std::optional<std::uint64_t> view_seed;
    // --memory-budget: the scene's memory in bytes (every mesh once: BVHs of the meshes that
    // stay BVH plus LSNIF assets) that conversion aims at; candidates are converted in order
    // of BVH bytes saved per asset byte until the scene fits, the rest stay BVH. 0 = none:
    // every candidate is converted. Missing it because candidates did not ship is a warning;
    // a budget below the meshes that stay BVH in any case is a usage error.
    std::uint64_t memory_budget = 0;
    // --bvh-yardstick: the BVH every memory figure, ratio, rule and budget compares an asset's
    // resident bytes with (ClassifyRule::yardstick); none = the preset's (Embree's BVH).
    std::optional<BvhYardstick> bvh_yardstick;
    // --memory-ratio: > 0 overrides ClassifyRule::min_memory_ratio, how many times smaller
    // than the yardstick's BVH an asset must be held to convert its mesh.
    double min_memory_ratio = 0;
    // Model overrides (0 = the preset's value), for sweeps such as scripts/tradeoff. A
    // changed table size is the largest the per-mesh sizing may choose.
    std::uint32_t log2_table_size = 0;        // T = 2^n rows per hashed level
    std::uint32_t first_log2_table_size = 0;  // Sizing::first_log2_table_size
    std::uint32_t max_points = 0;             // H, voxel entry points per ray
    std::uint32_t grid_resolution = 0;        // V, occupancy grid cells per axis
    std::uint32_t max_grid_resolution = 0;    // Sizing::max_grid_resolution
    std::uint32_t hidden_width = 0;           // width of both hidden layers
    bool no_ray_inputs = false;               // the MLP sees the points' features only (1.0/1.1 files)
};

// The split of --shard (ConvertOptions::shard_count) and of a library's plan
// (lsnif::library), longest processing time first: items (already in order, costliest
// first) dealt one after another to the shard (0..count-1) with the least cost so far, ties
// to the lowest index. Within 4/3 of the best split; a function of the costs alone, so every
// shard computes it.
std::vector<std::uint32_t> deal_to_shards(const std::vector<std::uint64_t>& costs, std::uint32_t count);

// Progress events: stage changes and training steps.
struct ProgressEvent {
    std::string mesh;
    std::string stage;  // import, classify, voxelize, sample, train, evaluate, write, done
    std::uint32_t step = 0, steps = 0;
    float loss = 0;
    double eta_seconds = 0;
    // Stage "done": the mesh's settled outcome (without its memory), valid during the call
    // only. Sent once per mesh, as soon as it is decided or converted.
    const MeshOutcome* outcome = nullptr;
};
using ConvertProgress = std::function<void(const ProgressEvent&)>;

// What the cache did in a run.
struct CacheCounts {
    std::size_t hits = 0, stored = 0, corrupt = 0;
    std::string location;  // the cache's directory or server (cache::Cache::describe)
};

struct ConvertResult {
    std::vector<InputRecord> inputs;    // every input, in the order given
    std::vector<MeshOutcome> meshes;    // every mesh of the inputs that imported, with its memory
    std::size_t instances = 0;          // instances of those meshes in the scene
    std::optional<SceneMemory> memory;  // set once the meshes were settled
    double import_seconds = 0;
    std::optional<CacheCounts> cache;      // with --cache
    std::string manifest_path, gltf_path;  // what was written; empty if nothing
    nlohmann::json manifest;               // what was written to OUTDIR/manifest.json (empty if nothing)
    std::vector<std::string> errors;       // "FILE: problem", one per failed input
    std::vector<std::string> warnings;
    // The options cannot be met whatever conversion does (a --memory-budget below the bytes
    // of the meshes that stay BVH in any case): `errors` says why, nothing was written, and
    // the CLI exits 2 as for any other usage error.
    bool usage_error = false;
    bool dry_run = false;
    bool ok() const { return errors.empty(); }
};

ConvertResult convert(const ConvertOptions& options, const ConvertProgress& progress = {});

// The threads each conversion of convert(options) uses: --threads (0 = the hardware's)
// shared by --jobs, at least 1.
std::uint32_t threads_per_job(const ConvertOptions& options);

// What the results of a conversion depend on besides its inputs and settings
// (docs/pipeline.md "Cache keys" argues each part): the sources lsnif was built from, the
// compiler and the flags a user added, and the libraries whose code reaches an asset or a
// record. Not the thread count, the CPU, -march or the build type: the canonical arithmetic
// gives the same bits across those (tested), so the release, portable and packaged builds
// of one source share cache entries. Computed once per process. Part of every cache key.
struct ToolIdentity {
    std::string version;   // lsnif's version
    std::string sources;   // SHA-256 of format/, trainer/, converter/, schema/ and the build files
    std::string compiler;  // "GNU 12.2.0"
    std::string flags;     // CMAKE_CXX_FLAGS (a -ffast-math there would change results)
    std::string embree;    // the Embree library loaded (ground truth, BVH bytes), e.g. "31305"
    std::string zstd;      // the zstd library loaded (the assets' compressed sections)
    std::string json;      // nlohmann_json (numbers in metadata and records)
    std::string digest;    // SHA-256 over all of the above
};
const ToolIdentity& tool_identity();

// The absolute path of the running executable (/proc/self/exe); "" when it cannot be read.
std::string executable_path();

// Human-readable summary of a run (what `lsnif convert` prints).
std::string convert_text(const ConvertResult& result);
// The machine-readable report of a run (`lsnif convert --json`): what every stage decided,
// the memory, the errors and warnings, the import time and the cache's counts.
nlohmann::json convert_report_json(const ConvertResult& result);

}  // namespace lsnif::converter
