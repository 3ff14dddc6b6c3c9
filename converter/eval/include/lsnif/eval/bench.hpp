// `lsnif bench ...`: throughput benchmarks (never timed unit tests: CONTRIBUTING.md).
//
// Each benchmark returns its result as a struct; bench_json writes it (--json: the keys
// scripts/bench_table and docs/investigations/ read), bench_text is what the command
// prints. Rates are per wall second; "thread-ns" figures multiply by the thread count. The
// scene benchmarks (memory, rays, convert) can fail: they return the problem as one
// "<file>: <problem>" line.
#pragma once

#include <lsnif/lsnif.h>
#include <lsnif/base/result.hpp>
#include <lsnif/converter/convert.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::eval {

struct BenchOptions {
    std::uint32_t threads = 2;
    double min_seconds = 2.0;  // per measurement
};

// Benchmarks of a conversion's objects against Embree, same machine, same run.
struct SceneBenchOptions {
    std::string outdir;                // a `lsnif convert` OUTDIR
    std::vector<std::string> sources;  // the converted inputs; empty = the manifest's paths
    std::uint32_t threads = 2;
    std::uint64_t rays = 1u << 20;  // rays: per object, all three families
    std::uint32_t repeats = 3;      // rays: best of
    std::uint64_t seed = 12345;
    lsnif_arithmetic arithmetic =
        LSNIF_ARITHMETIC_AUTO;  // LSNIF network arithmetic (auto: what lsnif_open picks)
};

// Where a train or infer benchmark ran: the v1 default model on this CPU.
struct BenchMachine {
    std::string model;  // the model's shape, one line
    std::string cpu;    // /proc/cpuinfo's model name, "unknown" without one
    std::uint32_t threads = 0;
};

// The training-shaped dense product (4096 x 108 -> 128), single-threaded, in GFLOP/s.
struct DenseKernelBench {
    std::string shape;
    double lsnif_gflops = 0, openblas_gflops = 0;
    // The bf16 kernel on the same product with K padded to 128, the padded FLOPs counted (what
    // the instructions execute); none without AVX-512 BF16.
    struct Bf16 {
        std::string shape;
        double lsnif_gflops = 0;
    };
    std::optional<Bf16> bf16;
};

// One training batch size in one MLP precision.
struct TrainRun {
    std::uint32_t batch_size = 0;
    trainer::MlpPrecision precision = trainer::MlpPrecision::fp32;
    int steps = 0;  // training steps timed
    double samples_per_second = 0;
    double mlp_gflops = 0;                  // the MLP products' FLOPs per second, GFLOP/s
    double mlp_fraction_of_sgemm = 0;       // mlp_gflops over TrainBench::sgemm_gflops_openblas_2048
    double prepare_rays_per_second = 0;     // Trainer::prepare on the batch's rays (geometry only)
    std::optional<double> speedup_vs_fp32;  // samples/s over the fp32 run's; bf16 runs only
};

// `lsnif bench train`: training throughput for batches 2^14..2^16, fp32 and (where the CPU
// has it) bf16 stepped in alternating slices, against the machine's sgemm rate.
struct TrainBench {
    BenchMachine machine;
    bool bf16_available = false;            // a bf16 backend ran (AMX or AVX-512 BF16)
    std::string bf16_arithmetic;            // trainer::mlp_arithmetic(bf16): "bf16/<instructions>" or "fp32"
    double sgemm_gflops_openblas_2048 = 0;  // OpenBLAS 2048^3 sgemm, all threads, GFLOP/s
    DenseKernelBench dense_kernel;
    std::vector<TrainRun> runs;  // by batch size, fp32 before bf16
};

// format::intersect over one set of rays, all threads.
struct IntersectRate {
    std::uint64_t rays = 0;  // rays in the set
    double rays_per_second = 0;
    double network_fraction = 0;  // of the rays, those that reached the network
    double culled_fraction = 0;   // of the rays, those occupancy culled
};

// One network arithmetic on the two ray sets: rays that all reach the network, and the
// training rays as generated (many leave early on occupancy).
struct InferRates {
    IntersectRate through_network, mixed_with_early_out;
};

// The pass's stages on rays that reach the network, cumulatively: each rate covers its stage
// and those before it, so differences of 1/rate are per-stage costs.
struct InferStages {
    double walk_scalar_rays_per_second = 0;  // format::trace_points, ray by ray
    double walk_rays_per_second = 0;         // format::trace_points_batch
    bool walk_16_lane = false;               // the batched walk runs 16 AVX-512 lanes
    double walk_encode_rays_per_second = 0;  // batched walk then format::encode_batch
};

// What holding the weights in fp16 costs the fp32 arithmetic, against the same values held
// in fp32: the median over timing turns of the per-turn speed ratios, and both runtimes' bytes.
struct WeightStorageCost {
    int turns = 0;
    double median_speed_ratio_fp16_over_fp32_storage = 0;
    std::uint64_t runtime_bytes_fp16_storage = 0, runtime_bytes_fp32_storage = 0;
};

// `lsnif bench infer`: the reader's forward pass in fp32 and in the reduced arithmetics this
// CPU has (bf16 on AVX-512 BF16, int8 on AVX-512 VNNI; none where it lacks them).
struct InferBench {
    BenchMachine machine;
    InferRates fp32;
    std::optional<InferRates> bf16, int8;
    InferStages stages;  // fp32 runtime
    WeightStorageCost fp16_weight_storage;
};

// Bytes of converted objects against the BVHs they replace. Ratios are BVH bytes over the
// asset's (an asset of 0 bytes counted as 1).
struct MemoryBytes {
    std::uint64_t lsnif_file_bytes = 0;
    std::uint64_t lsnif_resident_bytes = 0;            // lsnif_info.decoded_bytes with the fp32 network
    std::uint64_t embree_bvh_bytes = 0;                // Embree's BVH as built (device memory monitor)
    std::uint64_t bvh8_compressed_bytes_estimate = 0;  // sampling::CompressedBvh::bytes()
    double ratio_embree_over_resident() const;
    double ratio_bvh8_over_resident() const;
    double ratio_embree_over_file() const;
};

// One complex object of a conversion.
struct MemoryObject : MemoryBytes {
    std::string name;
    std::uint64_t triangles = 0;
    std::uint64_t instances = 0;
    std::uint64_t lsnif_resident_bytes_here = 0;  // decoded_bytes in arithmetic_here
    std::string arithmetic_here;                  // what SceneBenchOptions::arithmetic opened with
    std::uint64_t embree_device_bytes = 0;        // the BVH plus Embree's copies of the buffers
    std::uint64_t bvh8_inner_nodes = 0, bvh8_leaves = 0;
};

// `lsnif bench memory`: per complex object, the bytes a renderer holds once its asset is
// open (resident: with the fp32 network, the most any CPU holds; and with the arithmetic
// this CPU runs) and its file bytes, against Embree's BVH bytes for the same mesh and the
// compressed-BVH yardstick (sampling::CompressedBvh).
struct MemoryBench {
    std::string outdir;
    std::vector<MemoryObject> objects;
    MemoryBytes total;  // the objects' sums
};

// One complex object: the reader's batched inference against rtcIntersect1 and
// rtcIntersect16 on the same rays (all three families), each the best of the repeats.
struct RaysObject {
    std::string name;
    std::uint64_t triangles = 0;
    std::uint64_t rays = 0;
    std::uint32_t threads = 0;
    double lsnif_rays_per_second = 0;
    double rtcintersect1_rays_per_second = 0;
    double rtcintersect16_rays_per_second = 0;
    double hit_agreement = 0;      // fraction of the rays LSNIF and Embree both hit or both miss
    std::string lsnif_arithmetic;  // the network arithmetic the asset ran
    double ratio_lsnif_over_rtcintersect1() const;
    double ratio_lsnif_over_rtcintersect16() const;
    double time_ratio_lsnif_over_rtcintersect1() const;
};

// `lsnif bench rays`: every complex object of a conversion.
struct RaysBench {
    std::string outdir;
    std::vector<RaysObject> objects;
};

// One mesh of the conversion: its class and the wall seconds of the stages it ran.
struct ConvertObject {
    std::string name;
    converter::MeshClass cls = converter::MeshClass::simple;
    std::uint64_t triangles = 0;
    converter::Timings timings;
};

// `lsnif bench convert`: a conversion's wall time split by stage, in seconds.
struct ConvertBench {
    std::string preset;
    std::uint32_t threads = 0;  // ConvertOptions::threads as given (0 = the hardware's)
    double wall_seconds = 0;    // convert() as a whole
    double import_seconds = 0;  // importing the inputs (ConvertResult::import_seconds)
    std::vector<ConvertObject> objects;
    std::map<std::string, double> stage_totals;  // stage name -> seconds over all objects that ran it
};

TrainBench bench_train(const BenchOptions& options);
InferBench bench_infer(const BenchOptions& options);
base::Result<MemoryBench, std::string> bench_memory(const SceneBenchOptions& options);
base::Result<RaysBench, std::string> bench_rays(const SceneBenchOptions& options);
// Runs the conversion (writing options.outdir) and times it.
base::Result<ConvertBench, std::string> bench_convert(const converter::ConvertOptions& options);

nlohmann::json bench_json(const TrainBench& bench);
nlohmann::json bench_json(const InferBench& bench);
nlohmann::json bench_json(const MemoryBench& bench);
nlohmann::json bench_json(const RaysBench& bench);
nlohmann::json bench_json(const ConvertBench& bench);
std::string bench_text(const TrainBench& bench);
std::string bench_text(const InferBench& bench);
std::string bench_text(const MemoryBench& bench);
std::string bench_text(const RaysBench& bench);
std::string bench_text(const ConvertBench& bench);

}  // namespace lsnif::eval
