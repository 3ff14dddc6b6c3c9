// `lsnif bench ...`: throughput benchmarks (never timed unit tests; DEVELOPERS.md).
#pragma once

#include <nlohmann/json.hpp>

#include <cstdint>
#include <string>

namespace lsnif::converter {

struct BenchOptions {
    std::uint32_t threads = 2;
    double min_seconds = 2.0;  // per measurement
};

nlohmann::json bench_train(const BenchOptions& options);
nlohmann::json bench_infer(const BenchOptions& options);
std::string bench_text(const nlohmann::json& report);

}  // namespace lsnif::converter
