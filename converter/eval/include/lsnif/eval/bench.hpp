// `lsnif bench ...`: throughput benchmarks (never timed unit tests: CONTRIBUTING.md).
#pragma once

#include <lsnif/lsnif.h>
#include <lsnif/converter/convert.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
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
nlohmann::json bench_train(const BenchOptions& options);
// memory: per complex object, the bytes a renderer holds once its asset is open (resident:
// lsnif_info.decoded_bytes with the fp32 network, and with the arithmetic this CPU runs) and
// its file bytes, against Embree's BVH bytes for the same mesh (device memory monitor) and
// the compressed-BVH yardstick (sampling::CompressedBvh). Ratios are BVH over resident
// bytes. On failure returns null and sets `error`.
nlohmann::json bench_memory(const SceneBenchOptions& options, std::string& error);
// rays: the reader's batched inference against rtcIntersect1 and rtcIntersect16 on the same
// rays per object, as ratios, plus hit/miss agreement.
nlohmann::json bench_rays(const SceneBenchOptions& options, std::string& error);
// convert: runs the conversion and reports its wall time split by stage.
nlohmann::json bench_convert(const converter::ConvertOptions& options, std::string& error);
nlohmann::json bench_infer(const BenchOptions& options);
std::string bench_text(const nlohmann::json& report);
std::string bench_scene_text(const nlohmann::json& report);  // memory, rays, convert

}  // namespace lsnif::eval
