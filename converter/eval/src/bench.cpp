// `lsnif bench train` and `lsnif bench infer`: throughput of the trainer and of the
// reader's forward pass on the v1 default model, with the machine's sgemm rate (OpenBLAS)
// measured in the same run as the yardstick. Absolute times on shared machines are noisy;
// the ratios in one run are what docs/investigations/ records. `bench train` measures both MLP
// precisions (fp32, and bf16 on AMX when available) in alternating slices, so their ratio
// sees the same machine load.
#include <lsnif/analytic/spheres.hpp>
#include <lsnif/base/clock.hpp>
#include <lsnif/eval/bench.hpp>
#include <lsnif/format/bf16.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <cblas.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <lsnif/base/parallel.hpp>
#include <memory>
#include <span>

namespace lsnif::eval {

using nlohmann::json;
using Clock = std::chrono::steady_clock;

namespace {

using base::seconds_since;

std::string cpu_model() {
    std::ifstream f("/proc/cpuinfo");
    std::string line;
    while (std::getline(f, line))
        if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
    return "unknown";
}

// A scene of many small spheres: occupancy comparable to a detailed object.
analytic::SpheresSource bench_scene(const format::ModelDesc& d) {
    std::vector<analytic::Sphere> s;
    std::uint64_t x = 42;
    auto u = [&]() {
        x = x * 6364136223846793005ull + 1442695040888963407ull;
        return float(x >> 40) / float(1 << 24);
    };
    for (int i = 0; i < 24; ++i)
        s.push_back({{u() * 1.4f - 0.7f, u() * 1.4f - 0.7f, u() * 1.4f - 0.7f}, 0.05f + 0.2f * u()});
    return analytic::SpheresSource(std::move(s), d.box_min, d.box_max);
}

format::ModelDesc v1_desc() {
    format::ModelDesc d;  // the v1 model (docs/model.md "Coarse levels" for the presets): V=32, H=18, 64/128,
                          // T=2^17, F=3, 2x128
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    return d;
}

// OpenBLAS sgemm rate on large square matrices with `threads` threads: the machine's
// practical fp32 matrix-multiply peak for this run.
double sgemm_gflops(int n, int threads, double min_seconds) {
    openblas_set_num_threads(threads);
    std::vector<float> a(std::size_t(n) * n, 0.5f), b(std::size_t(n) * n, 0.25f), c(std::size_t(n) * n);
    cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, n, n, n, 1.f, a.data(), n, b.data(), n, 0.f,
                c.data(), n);
    int reps = 0;
    const auto t0 = Clock::now();
    do {
        cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, n, n, n, 1.f, a.data(), n, b.data(), n, 0.f,
                    c.data(), n);
        ++reps;
    } while (seconds_since(t0) < min_seconds);
    return 2.0 * double(n) * n * n * reps / seconds_since(t0) / 1e9;
}

// The training-shaped product (rows x 108 -> 128) single-threaded: ours vs OpenBLAS.
DenseKernelBench kernel_comparison(double min_seconds) {
    const int rows = 4096, in = 108, out = 128;
    std::vector<float> A(std::size_t(rows) * in, 0.3f), W(std::size_t(in) * out, 0.01f), bias(out, 0.f),
        C(std::size_t(rows) * out);
    auto rate = [&](auto&& fn) {
        fn();
        int reps = 0;
        const auto t0 = Clock::now();
        do {
            fn();
            ++reps;
        } while (seconds_since(t0) < min_seconds);
        return 2.0 * rows * in * out * reps / seconds_since(t0) / 1e9;
    };
    openblas_set_num_threads(1);
    const double ours = rate(
        [&] { format::dense_layer(A.data(), rows, in, in, W.data(), bias.data(), out, true, C.data()); });
    const double blas = rate([&] {
        cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, rows, out, in, 1.f, A.data(), in, W.data(),
                    out, 0.f, C.data(), out);
    });
    DenseKernelBench r{.shape = "4096x108 * 108x128, 1 thread",
                       .lsnif_gflops = ours,
                       .openblas_gflops = blas,
                       .bf16 = std::nullopt};
    // The bf16 kernel on the same product (K padded to 128 as the trainer and reader pad it;
    // the FLOPs counted are the padded ones the instructions execute): this machine's bf16
    // rate on our shapes, against which the bf16 MLP fractions are read.
    if (format::cpu_features().avx512_bf16) {
        const std::size_t kp = format::round_up(in, 32);
        std::vector<format::Bf16> a(std::size_t(rows) * kp), b(kp * 2 * out);
        format::pack_rows(A.data(), rows, in, in, a.data(), kp, rows);
        format::pack_vnni(W.data(), in, out, out, b.data(), 2 * out, kp);
        const double bf = rate([&] {
                              format::gemm_bf16_dp(rows, out, kp, a.data(), kp, b.data(), 2 * out, C.data(),
                                                   out, {bias.data(), true, false});
                          }) *
                          double(kp) / in;
        r.bf16 = DenseKernelBench::Bf16{"4096x128 * 128x128 (K padded), 1 thread", bf};
    }
    return r;
}

const char* const kModel = "V=32 H=18 levels 64,128 T=2^17 F=3 hidden 128x128 (v1)";

}  // namespace

TrainBench bench_train(const BenchOptions& o) {
    const format::ModelDesc d = v1_desc();
    analytic::SpheresSource src = bench_scene(d);
    std::vector<samples::Sample> raw;
    src.generate(1, 1u << 18, raw);
    TrainBench out;
    const double peak = sgemm_gflops(2048, int(o.threads), o.min_seconds);
    bool bf16_available = false;
    for (std::uint32_t b : {1u << 14, 1u << 15, 1u << 16}) {
        // One trainer per precision, same seed and batch; both are stepped in alternating
        // slices (kSlices each, min_seconds in total per precision) so a load change on a
        // shared machine hits both alike.
        struct Run {
            std::unique_ptr<trainer::Trainer> tr;
            int steps = 0;
            double seconds = 0;
        };
        std::array<Run, 2> slots;
        std::size_t count = 0;
        for (const auto p : {trainer::MlpPrecision::fp32, trainer::MlpPrecision::bf16}) {
            trainer::TrainConfig cfg;
            cfg.batch_size = b;
            cfg.threads = o.threads;
            cfg.steps = 1000000;
            cfg.mlp_precision = p;
            auto tr = std::make_unique<trainer::Trainer>(d, src.occupancy(d), cfg);
            if (tr->mlp_precision() != p) continue;  // bf16 without a bf16 backend: fp32 only
            slots[count++].tr = std::move(tr);
        }
        const std::span<Run> per(slots.data(), count);
        bf16_available = count == 2;
        const auto tp = Clock::now();
        const trainer::PreparedSet set = per[0].tr->prepare(raw);  // depends on geometry only
        const double prep_rays_per_second = double(raw.size()) / seconds_since(tp);
        std::vector<std::uint32_t> batch(b);
        for (std::size_t i = 0; i < b; ++i) batch[i] = std::uint32_t((i * 7919) % set.size());
        for (Run& r : per) r.tr->step(set, batch);  // warm-up: first-touch of all buffers
        constexpr int kSlices = 3;
        for (int slice = 0; slice < kSlices; ++slice)
            for (Run& r : per) {
                int steps = 0;
                const auto t0 = Clock::now();
                do {
                    r.tr->step(set, batch);
                    ++steps;
                } while (seconds_since(t0) < o.min_seconds / kSlices || steps < 1);
                r.seconds += seconds_since(t0);
                r.steps += steps;
            }
        double fp32_sps = 0;
        for (const Run& r : per) {
            const double sps = double(r.steps) * b / r.seconds;
            const double mlp_gflops = sps * r.tr->mlp_flops_per_sample() / 1e9;
            const bool fp32 = r.tr->mlp_precision() == trainer::MlpPrecision::fp32;
            if (fp32) fp32_sps = sps;
            TrainRun run{.batch_size = b,
                         .precision = r.tr->mlp_precision(),
                         .steps = r.steps,
                         .samples_per_second = sps,
                         .mlp_gflops = mlp_gflops,
                         .mlp_fraction_of_sgemm = mlp_gflops / peak,
                         .prepare_rays_per_second = prep_rays_per_second,
                         .speedup_vs_fp32 = fp32 ? std::nullopt : std::optional(sps / fp32_sps)};
            out.runs.push_back(run);
        }
    }
    out.machine = {kModel, cpu_model(), o.threads};
    out.bf16_available = bf16_available;
    out.bf16_arithmetic = trainer::mlp_arithmetic(trainer::MlpPrecision::bf16);
    out.sgemm_gflops_openblas_2048 = peak;
    out.dense_kernel = kernel_comparison(o.min_seconds);
    return out;
}

namespace {

// Rays per second of format::intersect on `rays` with `threads` threads, repeated for at
// least `min_seconds`, and the fractions of the rays that reached the network and that
// occupancy culled.
IntersectRate intersect_rate(const format::Runtime& rt, const std::vector<format::Ray>& rays,
                             std::uint32_t threads, double min_seconds) {
    std::vector<format::Hit> hits(rays.size());
    const std::uint32_t T = threads;
    const std::size_t per = (rays.size() + T - 1) / T;
    std::uint64_t total = 0;
    format::IntersectStats st;
    const auto t0 = Clock::now();
    do {
        std::vector<format::IntersectStats> part(T);
        base::run_on_threads(T, [&](std::uint32_t t) {
            const std::size_t b = std::min(rays.size(), t * per), e = std::min(rays.size(), b + per);
            part[t] =
                format::intersect(rt, std::span(rays).subspan(b, e - b), std::span(hits).subspan(b, e - b));
        });
        st = {};
        for (auto& p : part) st.inferred += p.inferred, st.culled += p.culled;
        total += rays.size();
    } while (seconds_since(t0) < min_seconds);
    const double secs = seconds_since(t0);
    return {rays.size(), double(total) / secs, double(st.inferred) / double(rays.size()),
            double(st.culled) / double(rays.size())};
}

// The pass's stages, cumulatively, on the rays that reach the network: each rate covers
// its stage and those before it, so 1/rate differences are per-stage costs.
InferStages stage_rates(const format::Runtime& rt, const std::vector<format::Ray>& reach,
                        std::uint32_t threads, double min_seconds) {
    constexpr std::size_t kChunk = 256;  // intersect()'s chunk
    auto rate = [&](auto&& chunk) {
        const std::uint32_t T = threads;
        const std::size_t per = (reach.size() + T - 1) / T;
        std::uint64_t total = 0;
        const auto t0 = Clock::now();
        do {
            base::run_on_threads(T, [&](std::uint32_t t) {
                std::vector<format::RayPoints> pts(kChunk);
                std::vector<format::TraceStatus> status(kChunk);
                std::vector<float> row(kChunk * rt.geo.input_width);
                const std::size_t b = std::min(reach.size(), t * per), e = std::min(reach.size(), b + per);
                for (std::size_t c = b; c < e; c += kChunk)
                    chunk(std::span(reach).subspan(c, std::min(kChunk, e - c)), pts, status, row);
            });
            total += reach.size();
        } while (seconds_since(t0) < min_seconds);
        return double(total) / seconds_since(t0);
    };
    const auto grid = rt.grid_views();
    auto scalar_walk = [&](std::span<const format::Ray> rays, auto& pts, auto& status, auto&) {
        for (std::size_t i = 0; i < rays.size(); ++i)
            status[i] = format::trace_points(rt.geo, rt.occupancy, rays[i], pts[i]);
    };
    auto walk = [&](std::span<const format::Ray> rays, auto& pts, auto& status, auto&) {
        format::trace_points_batch(rt.geo, rt.occupancy, rays, pts.data(), status.data());
    };
    auto walk_encode = [&](std::span<const format::Ray> rays, auto& pts, auto& status, auto& row) {
        walk(rays, pts, status, row);
        std::uint32_t which[kChunk];
        std::size_t k = 0;
        for (std::size_t i = 0; i < rays.size(); ++i)
            if (status[i] == format::TraceStatus::ok) which[k++] = std::uint32_t(i);
        format::encode_batch(rt.geo, grid.data(), pts.data(), std::span(which, k), row.data());
    };
    // Braced initializers run in order: the scalar walk, the batched walk, walk + encode.
    return {rate(scalar_walk), rate(walk), format::cpu_features().avx512, rate(walk_encode)};
}

// What holding the weights in fp16 costs the fp32 arithmetic: `rt` (a model's network, fp16
// W^T widened on load) against the same runtime with the same values stored in fp32, timed in
// turns on the rays that reach the network, and the median of the per-turn ratios (pairs
// keep the ratio meaningful on a machine whose speed drifts).
WeightStorageCost weight_storage_cost(const format::Runtime& rt, const format::ModelData& model,
                                      const std::vector<format::Ray>& reach, const BenchOptions& o) {
    format::Runtime fp32_stored = rt;
    std::vector<std::vector<float>> w, b;
    for (std::size_t k = 0; k < model.weights.size(); ++k) {
        w.push_back(format::halves_to_floats(model.weights[k]));
        b.push_back(format::halves_to_floats(model.biases[k]));
    }
    fp32_stored.net = format::make_network(model.desc, w, b);
    constexpr int kTurns = 5;
    std::vector<double> ratios;
    double fp16_rate = 0, fp32_rate = 0;
    for (int t = 0; t < kTurns; ++t) {
        fp16_rate = intersect_rate(rt, reach, o.threads, o.min_seconds / kTurns).rays_per_second;
        fp32_rate = intersect_rate(fp32_stored, reach, o.threads, o.min_seconds / kTurns).rays_per_second;
        ratios.push_back(fp16_rate / fp32_rate);
    }
    std::sort(ratios.begin(), ratios.end());
    return {kTurns, ratios[kTurns / 2], rt.heap_bytes(), fp32_stored.heap_bytes()};
}

}  // namespace

InferBench bench_infer(const BenchOptions& o) {
    const format::ModelDesc d = v1_desc();
    analytic::SpheresSource src = bench_scene(d);
    trainer::TrainConfig cfg;
    cfg.threads = o.threads;
    trainer::Trainer tr(d, src.occupancy(d), cfg);  // initialized weights: cost does not depend on values
    const format::ModelData model = tr.export_model("{}");
    std::vector<samples::Sample> raw;
    src.generate(2, 1u << 18, raw);
    std::vector<format::Ray> mix(raw.size());
    for (std::size_t i = 0; i < raw.size(); ++i) mix[i] = raw[i].ray;
    std::vector<format::Ray> reach;
    for (const auto& s : tr.reachable(raw)) reach.push_back(s.ray);

    auto run = [&](const format::Runtime& rt, const std::vector<format::Ray>& rays) {
        return intersect_rate(rt, rays, o.threads, o.min_seconds);
    };
    // fp32 (the reference; the top-level figures) and the reduced arithmetics the CPU has:
    // bf16 hidden layers (AVX-512 BF16) and int8 ones (AVX-512 VNNI, what lsnif_open picks
    // there).
    const format::Runtime rt32 = format::make_runtime(model, format::MlpArithmetic::fp32);
    InferBench r;
    r.machine = {kModel, cpu_model(), o.threads};
    r.fp32 = {run(rt32, reach), run(rt32, mix)};
    r.stages = stage_rates(rt32, reach, o.threads, o.min_seconds);
    r.fp16_weight_storage = weight_storage_cost(rt32, model, reach, o);
    const format::Runtime rt16 = format::make_runtime(model, format::MlpArithmetic::bf16);
    if (format::mlp_arithmetic(rt16.net) == format::MlpArithmetic::bf16)
        r.bf16 = InferRates{run(rt16, reach), run(rt16, mix)};
    const format::Runtime rt8 = format::make_runtime(model, format::MlpArithmetic::int8);
    if (format::mlp_arithmetic(rt8.net) == format::MlpArithmetic::int8)
        r.int8 = InferRates{run(rt8, reach), run(rt8, mix)};
    return r;
}

namespace {

json machine_json(const BenchMachine& m) {
    return {{"model", m.model}, {"cpu", m.cpu}, {"threads", m.threads}};
}

json kernel_json(const DenseKernelBench& k) {
    json j = {{"shape", k.shape}, {"lsnif_gflops", k.lsnif_gflops}, {"openblas_gflops", k.openblas_gflops}};
    if (k.bf16) {
        j["bf16_shape"] = k.bf16->shape;
        j["lsnif_bf16_gflops"] = k.bf16->lsnif_gflops;
    }
    return j;
}

json run_json(const TrainRun& r) {
    json j = {{"batch_size", r.batch_size},
              {"precision", trainer::precision_name(r.precision)},
              {"steps", r.steps},
              {"samples_per_second", r.samples_per_second},
              {"mlp_gflops", r.mlp_gflops},
              {"mlp_fraction_of_sgemm", r.mlp_fraction_of_sgemm},
              {"prepare_rays_per_second", r.prepare_rays_per_second}};
    if (r.speedup_vs_fp32) j["speedup_vs_fp32"] = *r.speedup_vs_fp32;
    return j;
}

json rate_json(const IntersectRate& r) {
    return {{"rays", r.rays},
            {"rays_per_second", r.rays_per_second},
            {"network_fraction", r.network_fraction},
            {"culled_fraction", r.culled_fraction}};
}

json rates_json(const InferRates& r) {
    return {{"through_network", rate_json(r.through_network)},
            {"mixed_with_early_out", rate_json(r.mixed_with_early_out)}};
}

json stages_json(const InferStages& s) {
    return {{"walk_scalar_rays_per_second", s.walk_scalar_rays_per_second},
            {"walk_rays_per_second", s.walk_rays_per_second},
            {"walk_16_lane", s.walk_16_lane},
            {"walk_encode_rays_per_second", s.walk_encode_rays_per_second}};
}

json storage_json(const WeightStorageCost& w) {
    return {{"turns", w.turns},
            {"median_speed_ratio_fp16_over_fp32_storage", w.median_speed_ratio_fp16_over_fp32_storage},
            {"runtime_bytes_fp16_storage", w.runtime_bytes_fp16_storage},
            {"runtime_bytes_fp32_storage", w.runtime_bytes_fp32_storage}};
}

std::string machine_text(const BenchMachine& m) {
    return "cpu: " + m.cpu + ", threads " + std::to_string(int(m.threads)) + "\nmodel: " + m.model + "\n";
}

}  // namespace

json bench_json(const TrainBench& b) {
    json j = machine_json(b.machine);
    j["benchmark"] = "train";
    j["bf16_available"] = b.bf16_available;
    j["bf16_arithmetic"] = b.bf16_arithmetic;
    j["sgemm_gflops_openblas_2048"] = b.sgemm_gflops_openblas_2048;
    j["dense_kernel"] = kernel_json(b.dense_kernel);
    j["runs"] = json::array();
    for (const TrainRun& r : b.runs) j["runs"].push_back(run_json(r));
    return j;
}

json bench_json(const InferBench& b) {
    json j = machine_json(b.machine);
    j["benchmark"] = "infer";
    // The fp32 figures at the top level: the reference the reduced arithmetics are read against.
    j.update(rates_json(b.fp32));
    j["stages"] = stages_json(b.stages);
    j["fp16_weight_storage"] = storage_json(b.fp16_weight_storage);
    if (b.bf16) j["bf16"] = rates_json(*b.bf16);
    if (b.int8) j["int8"] = rates_json(*b.int8);
    return j;
}

std::string bench_text(const TrainBench& r) {
    char buf[512];
    std::string s = machine_text(r.machine);
    std::snprintf(buf, sizeof buf, "OpenBLAS sgemm 2048^3: %.1f GFLOP/s\n", r.sgemm_gflops_openblas_2048);
    s += buf;
    const DenseKernelBench& k = r.dense_kernel;
    std::snprintf(buf, sizeof buf, "dense kernel %s: lsnif %.1f GFLOP/s, OpenBLAS %.1f GFLOP/s\n",
                  k.shape.c_str(), k.lsnif_gflops, k.openblas_gflops);
    s += buf;
    if (k.bf16) {
        std::snprintf(buf, sizeof buf, "bf16 kernel %s: lsnif %.1f GFLOP/s\n", k.bf16->shape.c_str(),
                      k.bf16->lsnif_gflops);
        s += buf;
    }
    if (!r.bf16_available)
        s += "bf16 MLP products: neither AMX nor AVX-512 BF16 on this machine, fp32 only\n";
    else
        s += "bf16 MLP products on " + r.bf16_arithmetic.substr(5) + "\n";
    for (const TrainRun& x : r.runs) {
        std::snprintf(buf, sizeof buf,
                      "batch %6d %-4s: %10.0f samples/s, MLP %.1f GFLOP/s (%.0f%% of sgemm); ray "
                      "preparation %.0f rays/s",
                      int(x.batch_size), trainer::precision_name(x.precision), x.samples_per_second,
                      x.mlp_gflops, 100 * x.mlp_fraction_of_sgemm, x.prepare_rays_per_second);
        s += buf;
        if (x.speedup_vs_fp32) {
            std::snprintf(buf, sizeof buf, "; %.2fx fp32", *x.speedup_vs_fp32);
            s += buf;
        }
        s += "\n";
    }
    return s;
}

std::string bench_text(const InferBench& r) {
    char buf[512];
    std::string s = machine_text(r.machine);
    const std::pair<const char*, const std::optional<InferRates>*> reduced[] = {{"bf16", &r.bf16},
                                                                                {"int8", &r.int8}};
    for (const auto& [key, set] : {std::pair{"through_network", &InferRates::through_network},
                                   std::pair{"mixed_with_early_out", &InferRates::mixed_with_early_out}}) {
        const IntersectRate& x = r.fp32.*set;
        std::snprintf(buf, sizeof buf, "%-22s fp32 %10.0f rays/s (%.0f%% reach the network)", key,
                      x.rays_per_second, 100 * x.network_fraction);
        s += buf;
        for (const auto& [a, rates] : reduced)
            if (*rates) {
                const double b = ((**rates).*set).rays_per_second;
                std::snprintf(buf, sizeof buf, "; %s %10.0f rays/s (%.2fx)", a, b, b / x.rays_per_second);
                s += buf;
            }
        s += "\n";
    }
    const InferStages& st = r.stages;
    const double T = int(r.machine.threads);
    const double walk1 = st.walk_scalar_rays_per_second, walk = st.walk_rays_per_second,
                 enc = st.walk_encode_rays_per_second;
    // The MLP + decode stage of each reduced arithmetic measured (fp32 where none was).
    std::string mlp;
    const auto stage = [&](const IntersectRate& through, const char* name) {
        const double ns = 1e9 * T * (1 / through.rays_per_second - 1 / enc);
        mlp += (mlp.empty() ? "" : ", ") + std::to_string(int(std::lround(ns))) + " (" + name + ")";
    };
    for (const auto& [a, rates] : reduced)
        if (*rates) stage((*rates)->through_network, a);
    if (mlp.empty()) stage(r.fp32.through_network, "fp32");
    std::snprintf(buf, sizeof buf,
                  "stages, thread-ns per ray reaching the network: walk %.0f (%s; scalar walk %.0f, %.2fx), "
                  "encode %.0f, MLP + decode %s\n",
                  1e9 * T / walk, st.walk_16_lane ? "16 lanes" : "scalar", 1e9 * T / walk1, walk / walk1,
                  1e9 * T * (1 / enc - 1 / walk), mlp.c_str());
    s += buf;
    const WeightStorageCost& ws = r.fp16_weight_storage;
    std::snprintf(buf, sizeof buf,
                  "fp32 arithmetic on fp16-stored weights: %.3fx the speed of fp32-stored ones (median of "
                  "%d turns), runtime %.0f KiB against %.0f KiB\n",
                  ws.median_speed_ratio_fp16_over_fp32_storage, ws.turns,
                  double(ws.runtime_bytes_fp16_storage) / 1024, double(ws.runtime_bytes_fp32_storage) / 1024);
    s += buf;
    return s;
}

}  // namespace lsnif::eval
