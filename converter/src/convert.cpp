// `lsnif convert`; see convert.hpp for the contracts.
#include <lsnif/base/clock.hpp>
#include <lsnif/cache/cache.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/converter/gltf_out.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/quantize.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/sampling/sampling.hpp>
#include <lsnif/scene/scene.hpp>
#include <lsnif/trainer/streamed.hpp>
#include <lsnif/voxelize/voxelize.hpp>
#include "convert_stages.hpp"

#include <algorithm>
#include <bit>
#include <cctype>
#include <charconv>
#include <chrono>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <limits>
#include <lsnif/base/parallel.hpp>
#include <memory>
#include <mutex>
#include <numeric>
#include <optional>
#include <set>
#include <thread>

namespace lsnif::converter {

using nlohmann::json;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

namespace {

using base::seconds_since;

std::uint64_t fnv1a64(const std::string& s, std::uint64_t h = 0xcbf29ce484222325ull) {
    for (unsigned char c : s) {
        h ^= c;
        h *= 0x100000001b3ull;
    }
    return h;
}

std::string hex16(std::uint64_t v) {
    char buf[17];
    std::snprintf(buf, sizeof buf, "%016" PRIx64, v);
    return buf;
}

json vec3(const std::array<float, 3>& v) {
    return json::array({v[0], v[1], v[2]});
}

// Index-connected components (vertices shared by index), union-find with path halving.
std::size_t count_components(const scene::Mesh& m) {
    std::vector<std::uint32_t> parent(m.vertex_count());
    std::iota(parent.begin(), parent.end(), 0u);
    auto find = [&](std::uint32_t x) {
        while (parent[x] != x) x = parent[x] = parent[parent[x]];
        return x;
    };
    std::vector<std::uint8_t> used(m.vertex_count(), 0);
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const std::uint32_t a = m.indices[3 * t], b = m.indices[3 * t + 1], c = m.indices[3 * t + 2];
        used[a] = used[b] = used[c] = 1;
        parent[find(a)] = find(b);
        parent[find(b)] = find(c);
    }
    std::size_t n = 0;
    for (std::uint32_t v = 0; v < parent.size(); ++v) n += used[v] && find(v) == v;
    return n;
}

double surface_area(const scene::Mesh& m) {
    double area = 0;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const float* p0 = &m.positions[3 * std::size_t(m.indices[3 * t])];
        const float* p1 = &m.positions[3 * std::size_t(m.indices[3 * t + 1])];
        const float* p2 = &m.positions[3 * std::size_t(m.indices[3 * t + 2])];
        const double e1[3] = {double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2]};
        const double e2[3] = {double(p2[0]) - p0[0], double(p2[1]) - p0[1], double(p2[2]) - p0[2]};
        const double c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};
        area += 0.5 * std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    }
    return area;
}

// Estimate of an asset's bytes for `d` with its grid stored as `encoding`, before training:
// header, table, occupancy and fp16 MLP uncompressed, 2 KiB of metadata, and the grid -
// uncompressed for fp16 (zstd gains under 10 % on it), divided by kU8GridCompression for
// 8 bits. Only a plan: the memory rule is checked again on the bytes actually chosen.
// zstd compressed trained 8-bit grids 1.51-2.18x on the meshes of BENCHMARKS.md "Sizing to
// the target"; the estimate assumes less.
constexpr double kU8GridCompression = 1.4;
std::uint64_t lsnif_bytes_estimate(format::ModelDesc d, format::GridEncoding encoding) {
    d.grid_encoding = encoding;
    const std::uint64_t mlp_values = d.parameter_count() - d.grid_value_count();
    const double grid = encoding == format::GridEncoding::u8_affine
                            ? double(d.grid_raw_size()) / kU8GridCompression
                            : double(d.grid_raw_size());
    return 64 + 64 * 5 + (d.voxel_count() + 7) / 8 + std::uint64_t(grid) + mlp_values * 2 + 2048;
}

// The smallest grid encoding the preset may ship.
format::GridEncoding smallest_encoding(const Preset& p) {
    return p.sizing.quantize ? format::GridEncoding::u8_affine : format::GridEncoding::fp16;
}

std::string gate_reason(const char* what, double value, const char* op, double limit, const char* unit) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "held-out %s %.4g%s %s gate %.4g%s", what, value, unit, op, limit, unit);
    return buf;
}

json family_json(const samples::FamilyMetrics& f) {
    return {{"rays", f.rays},
            {"visibility_accuracy", f.visibility_accuracy},
            {"false_hit_rate", f.false_hit_rate},
            {"false_miss_rate", f.false_miss_rate},
            {"distance_error_median_pct", f.distance_median_pct},
            {"distance_error_p95_pct", f.distance_p95_pct},
            {"normal_error_median_deg", f.normal_median_deg},
            {"normal_error_p95_deg", f.normal_p95_deg},
            {"geometric_normal_error_median_deg", f.geometric_normal_median_deg},
            {"culled_fraction", f.culled_fraction}};
}

// family_json read back (asset metadata of an earlier run): every field present and of its
// type, or nothing. No field defaults: a decision never reads a value nobody measured.
std::optional<samples::FamilyMetrics> family_from_json(const json& j) {
    if (!j.is_object()) return std::nullopt;
    samples::FamilyMetrics f;
    const std::pair<const char*, double*> numbers[] = {
        {"visibility_accuracy", &f.visibility_accuracy},
        {"false_hit_rate", &f.false_hit_rate},
        {"false_miss_rate", &f.false_miss_rate},
        {"distance_error_median_pct", &f.distance_median_pct},
        {"distance_error_p95_pct", &f.distance_p95_pct},
        {"normal_error_median_deg", &f.normal_median_deg},
        {"normal_error_p95_deg", &f.normal_p95_deg},
        {"geometric_normal_error_median_deg", &f.geometric_normal_median_deg},
        {"culled_fraction", &f.culled_fraction}};
    for (const auto& [key, field] : numbers) {
        if (!j.contains(key) || !j[key].is_number()) return std::nullopt;
        *field = j[key].get<double>();
    }
    if (!j.contains("rays") || !j["rays"].is_number_unsigned()) return std::nullopt;
    f.rays = j["rays"].get<std::uint64_t>();
    return f;
}

json model_json(const format::ModelDesc& d) {
    return {{"grid_resolution", d.grid_resolution},
            {"max_points", d.max_points},
            {"level_resolutions", d.level_resolution},
            {"features_per_level", d.features_per_level},
            {"log2_table_size", d.log2_table_size},
            {"hidden_widths", d.hidden_width},
            {"output_count", d.output_count()},
            {"material_count", d.material_count},
            {"activation", "relu"},
            {"distance_encoding", distance_encoding_name(d.distance_encoding)},
            {"grid_encoding", grid_encoding_name(std::uint32_t(d.grid_encoding))},
            {"ray_inputs", ray_inputs_name(d.ray_inputs)},
            {"normal", "shading"},
            {"parameter_count", d.parameter_count()}};
}

}  // namespace

std::vector<std::string> gate_failures(const samples::Metrics& m, const Gate& g) {
    std::vector<std::string> fails;
    if (m.pooled.visibility_accuracy < g.min_visibility)
        fails.push_back(gate_reason("visibility accuracy", 100 * m.pooled.visibility_accuracy, "<",
                                    100 * g.min_visibility, "%"));
    for (int f = 0; f < samples::kFamilyCount; ++f)
        if (m.family[f].rays < g.min_family_rays)
            fails.push_back(std::string("held-out ") + samples::family_name(samples::Family(f)) +
                            " rays reaching the network: " + std::to_string(m.family[f].rays) + " < " +
                            std::to_string(g.min_family_rays) + " (too few to measure)");
    for (int f = 0; f < samples::kFamilyCount; ++f)
        if (m.family[f].rays && m.family[f].visibility_accuracy < g.min_family_visibility)
            fails.push_back(
                gate_reason((std::string(samples::family_name(samples::Family(f))) + " visibility").c_str(),
                            100 * m.family[f].visibility_accuracy, "<", 100 * g.min_family_visibility, "%"));
    if (m.pooled.distance_median_pct > g.max_distance_median_pct)
        fails.push_back(gate_reason("median distance error", m.pooled.distance_median_pct, ">",
                                    g.max_distance_median_pct, "% of diagonal"));
    if (m.pooled.normal_median_deg > g.max_normal_median_deg)
        fails.push_back(gate_reason("median normal error", m.pooled.normal_median_deg, ">",
                                    g.max_normal_median_deg, " deg"));
    return fails;
}

bool parse_target(const std::string& text, Target& target, std::string& error) {
    double v[3];
    std::size_t pos = 0;
    for (int i = 0; i < 3; ++i) {
        const std::size_t end = text.find(',', pos);
        if ((end == std::string::npos) != (i == 2)) {
            error = "expected VIS,DIST,NORMAL (three numbers, e.g. 97,1.0,15)";
            return false;
        }
        const std::string part = text.substr(pos, end == std::string::npos ? std::string::npos : end - pos);
        char* stop = nullptr;
        v[i] = std::strtod(part.c_str(), &stop);
        if (part.empty() || *stop != '\0' || !std::isfinite(v[i])) {
            error = "'" + part + "' is not a number (expected VIS,DIST,NORMAL, e.g. 97,1.0,15)";
            return false;
        }
        pos = end + 1;
    }
    char why[160] = "";
    if (!(v[0] > 0 && v[0] <= 100))
        std::snprintf(why, sizeof why, "visibility %g %% is outside (0, 100]", v[0]);
    else if (!(v[1] > 0 && v[1] <= 100))
        std::snprintf(why, sizeof why, "distance error %g %% of the diagonal is outside (0, 100]", v[1]);
    else if (!(v[2] > 0 && v[2] <= 180))
        std::snprintf(why, sizeof why, "normal error %g degrees is outside (0, 180]", v[2]);
    if (why[0]) {
        error = why;
        return false;
    }
    target = {v[0] / 100.0, v[1], v[2]};
    return true;
}

bool parse_byte_size(const std::string& text, std::uint64_t& bytes, std::string& error) {
    std::size_t digits = 0;
    while (digits < text.size() &&
           (std::isdigit(static_cast<unsigned char>(text[digits])) || text[digits] == '.'))
        ++digits;
    double value = 0;
    const std::string number = text.substr(0, digits);
    const auto [end, ec] = std::from_chars(number.data(), number.data() + number.size(), value);
    if (number.empty() || ec != std::errc() || end != number.data() + number.size()) {
        error = "expected a byte count such as 1500000, 512K, 64MiB or 1.5G";
        return false;
    }
    std::string unit;
    for (char ch : text.substr(digits)) unit += char(std::tolower(static_cast<unsigned char>(ch)));
    double scale = 1;
    const std::string prefixes = "kmgt";  // 1024^1 .. 1024^4
    if (const std::size_t k = unit.empty() ? std::string::npos : prefixes.find(unit[0]);
        k != std::string::npos) {
        scale = std::ldexp(1.0, 10 * int(k + 1));
        unit.erase(0, 1);
        if (unit == "ib") unit = "b";
    }
    if (!unit.empty() && unit != "b") {
        error = "unknown unit '" + text.substr(digits) + "' (use K, M, G or T: powers of 1024)";
        return false;
    }
    const double total = std::floor(value * scale);
    if (!(total >= 1)) {
        error = "must be at least 1 byte";
        return false;
    }
    if (total > 9.2e18) {
        error = "more than 2^63 bytes";
        return false;
    }
    bytes = std::uint64_t(total);
    return true;
}

std::vector<std::string> target_misses(const samples::FamilyMetrics& p, const Target& t) {
    std::vector<std::string> misses;
    char buf[160];
    const double vis = p.visibility_accuracy, dist = p.distance_median_pct, normal = p.normal_median_deg;
    if (vis < t.visibility) {
        std::snprintf(buf, sizeof buf, "visibility %.2f %% < target %.2f %%", 100 * vis, 100 * t.visibility);
        misses.push_back(buf);
    }
    if (dist > t.distance_pct) {
        std::snprintf(buf, sizeof buf, "median distance error %.3g %% > target %.3g %%", dist,
                      t.distance_pct);
        misses.push_back(buf);
    }
    if (normal > t.normal_deg) {
        std::snprintf(buf, sizeof buf, "median normal error %.3g deg > target %.3g deg", normal,
                      t.normal_deg);
        misses.push_back(buf);
    }
    return misses;
}

json validation_json(std::span<const ValidationPoint> curve) {
    json j = json::array();
    for (const ValidationPoint& p : curve)
        j.push_back({{"step", p.step},
                     {"visibility", p.visibility},
                     {"distance_pct", p.distance_pct},
                     {"normal_deg", p.normal_deg}});
    return j;
}

std::vector<std::string> early_abort_reasons(const ValidationPoint& point, std::uint64_t samples,
                                             const Gate& g, const EarlyAbort& rule) {
    std::vector<std::string> why;
    if (samples < rule.min_samples) return why;
    char buf[200];
    const double vis = point.visibility;
    if (vis + rule.visibility_headroom < g.min_visibility) {
        std::snprintf(buf, sizeof buf, "validation visibility %.1f %% cannot reach the gate's %.1f %%",
                      100 * vis, 100 * g.min_visibility);
        why.push_back(buf);
    }
    const double normal = point.normal_deg;
    if (normal - rule.normal_headroom_deg > g.max_normal_median_deg) {
        std::snprintf(buf, sizeof buf, "validation normal error %.1f deg cannot reach the gate's %.1f deg",
                      normal, g.max_normal_median_deg);
        why.push_back(buf);
    }
    const double dist = point.distance_pct;
    if (dist * rule.distance_factor > g.max_distance_median_pct) {
        std::snprintf(buf, sizeof buf, "validation distance error %.2f %% cannot reach the gate's %.2f %%",
                      dist, g.max_distance_median_pct);
        why.push_back(buf);
    }
    return why;
}

Target effective_target(const Target& t, const Gate& g) {
    return {std::max(t.visibility, g.min_visibility), std::min(t.distance_pct, g.max_distance_median_pct),
            std::min(t.normal_deg, g.max_normal_median_deg)};
}

bool meets_target_with_margin(const ValidationPoint& point, const Target& t, const TargetStop& rule) {
    return point.visibility >= t.visibility + rule.visibility_margin &&
           point.distance_pct <= t.distance_pct * rule.distance_factor &&
           point.normal_deg <= t.normal_deg - rule.normal_margin_deg;
}

std::string falls_behind(const ValidationPoint& point, std::span<const ValidationPoint> larger,
                         const Target& target, const TargetStop& stop, const Sizing& rule) {
    // The larger rung's visibility at the last check at or before the point's step, and the
    // most it gained from there on.
    const std::uint32_t step = point.step;
    const ValidationPoint* at = nullptr;
    for (const ValidationPoint& q : larger)
        if (q.step <= step) at = &q;
    if (!at || larger.back().step < step) return {};
    double best = 0;
    for (const ValidationPoint& q : larger)
        if (q.step >= at->step) best = std::max(best, q.visibility);
    const double gain = best - at->visibility;
    const double vis = point.visibility, needed = target.visibility + stop.visibility_margin;
    if (vis + gain + rule.curve_slack >= needed) return {};
    char buf[240];
    std::snprintf(buf, sizeof buf,
                  "validation visibility %.2f %% at step %u; the larger model gained %.2f points after that "
                  "step, short of the %.2f %% needed",
                  100 * vis, step, 100 * gain, 100 * needed);
    return buf;
}

json metrics_json(const samples::Metrics& m) {
    return {{"outside", family_json(m.family[0])},
            {"surface", family_json(m.family[1])},
            {"interior", family_json(m.family[2])},
            {"pooled", family_json(m.pooled)}};
}

// Everything else that changes the trained weights: the recipe (bump kRecipeVersion when
// sampling or training code changes its streams) and the arithmetic (arithmetic_id: the
// canonical arithmetic's version, or the instructions of the machine arithmetic). The thread
// count is not part of it: it never changes a result.
constexpr int kRecipeVersion = 5;
static std::string recipe_key(const Preset& p, Arithmetic arithmetic) {
    const trainer::TrainConfig& c = p.train;
    char buf[512];
    std::snprintf(buf, sizeof buf, "r%d|%s|lw%g,%g,%g,%g|g%g,%g,%g,%g|m%g,%g,%g,%g,%g|d%g,%g,%g,%g|n%d,%g",
                  kRecipeVersion, arithmetic_id(arithmetic).c_str(), c.loss.visibility, c.loss.distance,
                  c.loss.normal, c.loss.material, c.grid_adam.lr, c.grid_adam.beta1, c.grid_adam.beta2,
                  c.grid_adam.eps, c.mlp_adam.lr, c.mlp_adam.beta1, c.mlp_adam.beta2, c.mlp_adam.eps,
                  c.mlp_adam.l2, c.decay_start, c.final_lr_fraction, c.huber_delta, c.grad_clip_norm,
                  int(c.normal_loss), c.normal_chord_epsilon);
    return buf;
}

// The rules that decide which weights ship: the target with its stop margins, the abort
// rule, the validation checks, the sizing ladder and pruning. Part of the asset key, since
// they decide how many steps the weights saw, which size and encoding was kept and which of
// its neurons.
static std::string stop_key(const Target& t, const Preset& p) {
    const TargetStop& s = p.target_stop;
    const EarlyAbort& a = p.early_abort;
    const Sizing& z = p.sizing;
    char buf[320];
    std::snprintf(
        buf, sizeof buf,
        "target%g,%g,%g|stop%u,%g,%g,%g|abort%llu,%g,%g,%g|checks%u,%llu|sizing%d,%d,%g,%u,%g|prune%d",
        t.visibility, t.distance_pct, t.normal_deg, s.consecutive, s.visibility_margin, s.distance_factor,
        s.normal_margin_deg, (unsigned long long)a.min_samples, a.visibility_headroom, a.normal_headroom_deg,
        a.distance_factor, p.validation_checks, (unsigned long long)p.validation_rays, int(z.explore_smaller),
        int(z.quantize), z.curve_slack, p.classify.min_log2_table_size, p.classify.min_memory_ratio,
        int(p.prune_inactive));
    return buf;
}

std::vector<std::string> preset_names() {
    return {"default", "fast", "quality", "smoke"};
}

bool find_preset(const std::string& name, Preset& p) {
    p = Preset{};
    p.name = name;
    // v1 model of docs/architecture.md §3 in every preset; presets trade training time for accuracy.
    // Measured on the dragon (BENCHMARKS.md "Conversion", 2^23 streamed rays, bf16 MLP):
    // at equal samples, more and smaller steps win slightly (1200 x 16384: 97.21 %, 0.90 %,
    // 14.1 deg in 77 s of training; 2400 x 8192: 97.46 %, 0.85 %, 12.8 deg in 83 s).
    p.train.batch_size = 1u << 13;
    // The normal loss is the smoothed chord (trainer.hpp NormalLoss) at weight 0.7: on CGAL's
    // dragon and armadillo at the full budget the median normal error drops 1.1-1.4 degrees
    // with visibility and distance as good or better than the cosine loss at weight 2
    // (docs/model.md "The normal loss").
    p.train.normal_loss = trainer::NormalLoss::chord;
    p.train.loss.normal = 0.7f;
    // The MLP also sees the ray's unit direction and its entry points' offsets along it:
    // on CGAL's dragon and armadillo, three seeds each, every held-out metric improved on
    // every seed (docs/model.md "Ray inputs").
    p.model.ray_inputs = format::kRayInputDirection | format::kRayInputEntryOffsets;
    // Levels 16, 32 and 128 instead of v1's 64 and 128: the two coarse levels are dense
    // (17^3 and 33^3 rows), so the grid is smaller, and on CGAL's dragon and armadillo every
    // held-out metric of three seeds beats v1's (docs/model.md "Coarse levels").
    p.model.level_resolution = {16, 32, 128};
    // At most 14 entry points instead of 18: the third level makes inference slower (a
    // coarse level's points have up to 8 live corners, the first layer has more inputs);
    // fewer slots give part of that back, with held-out metrics within a seed's noise
    // (docs/model.md "Coarse levels").
    p.model.max_points = 14;
    // A 64^3 occupancy grid instead of 32^3: entry points twice as dense along the ray and
    // closer to the surface. On CGAL's dragon and armadillo it is what moved held-out
    // visibility past 98.5 % (issue #15 item 1), with the same 14 points and a smaller
    // asset; the longer voxel walk costs tracing time (BENCHMARKS.md "A 64^3 grid").
    p.model.grid_resolution = 64;
    // Visibility weighs twice the other losses: with the finer grid the distance and normal
    // errors sit well inside the default target, and the weight turns part of that margin
    // into visibility (docs/model.md "A 64^3 grid").
    p.train.loss.visibility = 2.0f;
    // The learning rate decays from 60 % of the steps (was 40 %) to 10 % of its start (was
    // 5 %): with the coarse levels the model still gains from the higher rate, most of all
    // on the surface family (docs/model.md "Coarse levels", the schedule).
    p.train.decay_start = 0.6f;
    p.train.final_lr_fraction = 0.1f;
    if (name == "default") {
        // 1200 steps: a conversion in under 20 s on a 2-core machine (issue #14). With the
        // chord normal loss and the ray inputs the fixed model reaches at 1200 steps what
        // the cosine loss reached at 2400 (BENCHMARKS.md "Conversion in 20 s").
        p.train.steps = 1200;
        p.train_rays = 1u << 23;
    } else if (name == "fast") {
        p.train.batch_size = 1u << 14;
        p.train.steps = 300;
        p.train_rays = 1u << 21;
    } else if (name == "quality") {
        p.train.batch_size = 1u << 12;
        p.train.steps = 4800;
        p.train_rays = 1u << 23;
    } else if (name == "smoke") {
        // Pipeline check in seconds (tests, CI): a small model and a lenient gate that only
        // rejects an untrained network. Not for shipping assets.
        p.model.grid_resolution = 16;
        p.model.max_points = 8;
        p.model.level_resolution = {32, 64};
        p.model.features_per_level = 2;
        p.model.log2_table_size = 12;
        p.model.hidden_width = {32, 32};
        p.train.batch_size = 2048;
        p.train.steps = 400;
        p.train_rays = 1u << 15;
        p.train_chunk_rays = 1u << 14;  // two rounds: exercises the streaming path
        p.eval_rays = 1u << 13;
        p.classify.min_triangles = 100;
        p.gate = {0.75, 0.6, 25.0, 90.0};
    } else {
        return false;
    }
    return true;
}

namespace stages {

// ---- the stages of one run -------------------------------------------------------------
//
// convert() imports each input, then takes every mesh through
//   classify -> voxelize -> (reuse | sample + train -> gate -> write asset)
// and finally writes the manifest. Each stage is a function below; a stage that decides
// "simple" returns nothing and the mesh is recorded with its reason.

bool resolve_preset(const ConvertOptions& opt, Preset& preset, std::string& error) {
    if (!find_preset(opt.preset, preset)) {
        std::string names;
        for (const auto& n : preset_names()) names += (names.empty() ? "" : ", ") + n;
        error = "unknown preset '" + opt.preset + "' (known: " + names + ")";
        return false;
    }
    if (opt.gate_min_visibility >= 0) preset.gate.min_visibility = opt.gate_min_visibility;
    if (opt.steps > 0) preset.train.steps = opt.steps;
    if (opt.batch_size > 0) preset.train.batch_size = opt.batch_size;
    if (opt.log2_table_size > 0) preset.model.log2_table_size = opt.log2_table_size;
    if (opt.max_points > 0) preset.model.max_points = opt.max_points;
    if (opt.grid_resolution > 0) preset.model.grid_resolution = opt.grid_resolution;
    if (opt.hidden_width > 0)
        for (auto& w : preset.model.hidden_width) w = opt.hidden_width;
    if (opt.no_ray_inputs) preset.model.ray_inputs = 0;
    if (opt.fixed_model) {
        preset.sizing.explore_smaller = false;
        preset.sizing.quantize = false;
        preset.target_stop.consecutive = 0;
    }
    if (opt.no_give_up) preset.early_abort.min_samples = std::numeric_limits<std::uint64_t>::max();
    if (opt.keep_inactive) preset.prune_inactive = false;
    preset.train.mlp_precision = opt.arithmetic == Arithmetic::machine ? trainer::MlpPrecision::automatic
                                                                       : trainer::MlpPrecision::fp32;
    return true;
}

std::string range_problem(const mesh::Box& box) {
    double extent = 0, coord = 0;
    for (int a = 0; a < 3; ++a) {
        extent = std::max(extent, double(box.max[a]) - box.min[a]);
        coord = std::max({coord, std::fabs(double(box.min[a])), std::fabs(double(box.max[a]))});
    }
    if (extent >= kMinModelExtent && extent <= kMaxModelExtent && coord <= kMaxModelExtent) return {};
    char why[200];
    std::snprintf(why, sizeof why,
                  "box extent %.3g (coordinates up to %.3g) is outside the range LSNIF models in "
                  "single precision [%g, %g]",
                  extent, coord, kMinModelExtent, kMaxModelExtent);
    return why;
}

std::optional<Candidate> classify(const Run& run, const scene::Mesh& mesh, bool forced_complex,
                                  MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "classify"});
    Candidate c;
    c.forced = forced_complex;
    const ClassifyRule& rule = run.preset.classify;
    c.view = view_of(mesh);
    auto box = voxelize::padded_box(c.view);
    if (!box) {
        rec.reasons.push_back("cannot bound the mesh: " + box.error().message);
        return std::nullopt;
    }
    c.box = *box;
    if (std::string why = range_problem(c.box); !why.empty()) {
        rec.reasons.push_back(why);
        return std::nullopt;
    }
    c.desc = run.preset.model;
    c.desc.box_min = c.box.min;
    c.desc.box_max = c.box.max;
    sampling::SamplingConfig scfg;
    scfg.threads = run.threads;
    std::string serr;
    c.source = sampling::EmbreeSource::create(c.view, c.box, scfg, serr);
    if (!c.source) {
        rec.reasons.push_back("Embree could not build the mesh: " + serr);
        return std::nullopt;
    }
    const std::uint64_t bvh = c.source->bvh_bytes();
    // Size the tables to the mesh (ClassifyRule): halve T while the asset would not beat
    // the BVH. Levels dense at the preset size stay dense (fewer rows than T).
    if (!c.forced)
        while (c.desc.log2_table_size > rule.min_log2_table_size &&
               double(bvh) < rule.min_memory_ratio *
                                 double(lsnif_bytes_estimate(c.desc, smallest_encoding(run.preset))))
            --c.desc.log2_table_size;
    const double ext[3] = {double(c.box.max[0]) - c.box.min[0], double(c.box.max[1]) - c.box.min[1],
                           double(c.box.max[2]) - c.box.min[2]};
    const double box_area = 2 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2]);
    rec.stats = {{"box_min", vec3(c.box.min)},
                 {"box_max", vec3(c.box.max)},
                 {"area_ratio", surface_area(mesh) / box_area},
                 {"components", count_components(mesh)},
                 {"closed", c.source->is_closed()},
                 {"solid", c.source->rejects_interior()},
                 {"log2_table_size", c.desc.log2_table_size},
                 {"bvh_bytes", bvh},
                 {"lsnif_bytes_estimate", lsnif_bytes_estimate(c.desc, smallest_encoding(run.preset))}};
    rec.timings["classify"] = seconds_since(t0);
    return c;
}

std::optional<voxelize::Occupancy> voxelize_mesh(const Run& run, const scene::Mesh& mesh, const Candidate& c,
                                                 MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "voxelize"});
    voxelize::Options vopt;
    vopt.threads = run.threads;
    auto occ = voxelize::voxelize(c.view, c.box, c.desc.grid_resolution, vopt);
    if (!occ) {
        rec.reasons.push_back("voxelization failed: " + occ.error().message);
        return std::nullopt;
    }
    rec.stats["occupied_fraction"] = double(occ->count()) / double(c.desc.voxel_count());
    rec.timings["voxelize"] = seconds_since(t0);
    return std::move(*occ);
}

bool worth_an_lsnif(const Run& run, const scene::Mesh& mesh, const Candidate& c, MeshRecord& rec) {
    const std::uint64_t bvh = c.source->bvh_bytes(),
                        est = lsnif_bytes_estimate(c.desc, smallest_encoding(run.preset));
    const double ratio = double(bvh) / double(est);
    const ClassifyRule& rule = run.preset.classify;
    char why[200];
    std::snprintf(why, sizeof why, "Embree BVH %" PRIu64 " bytes vs LSNIF %" PRIu64 " bytes (%.2fx)", bvh,
                  est, ratio);
    rec.reasons.push_back(why);
    if (!c.forced && ratio < rule.min_memory_ratio) {
        std::snprintf(why, sizeof why, "memory benefit %.2fx below the %.2fx threshold", ratio,
                      rule.min_memory_ratio);
        rec.reasons.push_back(why);
        return false;
    }
    if (c.forced)
        rec.reasons.push_back("forced complex by --complex " + mesh.name);
    else
        rec.reasons.push_back(std::to_string(mesh.triangle_count()) + " triangles");
    if (c.desc.log2_table_size != run.preset.model.log2_table_size)
        rec.reasons.push_back("hash tables sized to 2^" + std::to_string(c.desc.log2_table_size) +
                              " rows (preset 2^" + std::to_string(run.preset.model.log2_table_size) +
                              ") to beat the BVH's memory");
    return true;
}

std::string asset_key(const Run& run, const scene::Mesh& mesh, const format::ModelDesc& desc) {
    const Preset& p = run.preset;
    return scene::geometry_hash(mesh) + "|" + p.name + "|" + std::to_string(run.opt.seed) + "|" +
           std::to_string(p.train.steps) + "|" + std::to_string(p.train.batch_size) + "|" +
           std::to_string(p.train_rays) + "/" + std::to_string(p.train_chunk_rays) + "/" +
           std::to_string(p.train_window_chunks) + "|" + model_json(desc).dump() + "|" +
           recipe_key(p, run.opt.arithmetic) + "|" + stop_key(run.opt.target, p) + "|" +
           mesh_settings_key(run.opt);
}

std::optional<Reused> reusable_metrics(const fs::path& asset, const std::string& key) {
    std::error_code ec;
    if (!fs::exists(asset, ec)) return std::nullopt;
    auto bytes = format::read_file_bytes(asset.string());
    if (!bytes) return std::nullopt;
    auto model = format::read_model(*bytes);
    if (!model) return std::nullopt;
    json meta = json::parse(model->metadata_json, nullptr, false);
    if (!meta.is_object() || !meta.contains("metrics") || !meta["metrics"].contains("gate") ||
        meta.value("extensions", json::object()).value("lsnif_convert_key", "") != key)
        return std::nullopt;
    const json& families = meta["metrics"].value("families", json());
    const auto pooled = family_from_json(families.is_object() ? families.value("pooled", json()) : json());
    if (!pooled) return std::nullopt;  // not metrics this version writes: convert again
    return Reused{meta["metrics"], *pooled};
}

ValidationPoint validation_point(std::uint32_t step, const format::ModelData& model,
                                 std::span<const samples::Sample> rays, std::uint32_t threads) {
    const samples::Metrics m = samples::held_out_metrics(format::make_runtime(model), rays, threads);
    return {step, m.pooled.visibility_accuracy, m.pooled.distance_median_pct, m.pooled.normal_median_deg};
}

MeasureRays draw_measure_rays(const Run& run, const scene::Mesh& mesh, Candidate& c, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "sample"});
    MeasureRays rays;
    std::vector<sampling::SampleExtras> extras;
    c.source->generate(run.opt.seed * 2 + 1 + 0x5bd1e995ull, run.preset.eval_rays, rays.held_out, &extras);
    rays.held_out_geometric_normals.resize(extras.size());
    for (std::size_t i = 0; i < extras.size(); ++i)
        rays.held_out_geometric_normals[i] = extras[i].geometric_normal;
    c.source->generate(run.opt.seed * 2 + 1 + 0x27d4eb2full, run.preset.validation_rays, rays.validation);
    rec.add_seconds("sample", seconds_since(t0));
    return rays;
}

Trained train_rung(const Run& run, const scene::Mesh& mesh, Candidate& c, const format::ModelDesc& desc,
                   const voxelize::Occupancy& occ, const MeasureRays& rays, std::uint32_t steps,
                   std::span<const ValidationPoint> larger, MeshRecord& rec) {
    const auto t0 = Clock::now();
    Trained t;
    t.config = run.preset.train;
    t.config.steps = steps;
    t.config.threads = run.threads;
    t.config.seed = run.opt.seed;
    trainer::Trainer tr(desc, occ.bits, t.config);
    // Rays in proportion to the steps: a rung trained on part of the budget sees the same
    // rays per step as the full schedule.
    const Preset& p = run.preset;
    trainer::StreamPlan plan;
    plan.total_rays = std::max<std::uint64_t>(1, p.train_rays * steps / std::max(1u, p.train.steps));
    plan.rays_per_round = p.train_chunk_rays;
    plan.window_rounds = p.train_window_chunks;
    const std::uint64_t seed = run.opt.seed;
    plan.round_seed = [seed](std::uint64_t r) {
        return fnv1a64("train|" + std::to_string(seed) + "|" + std::to_string(r));
    };
    const std::uint32_t checks = p.validation_checks;
    std::uint32_t next_check = 1;  // check k runs once k * steps / checks steps are done
    std::uint32_t met_in_a_row = 0;
    double validation_seconds = 0;
    // At each validation check: give up when the gate is out of reach or a smaller rung
    // cannot catch up; stop when the target is met (TargetStop).
    const Target aim = effective_target(run.opt.target, p.gate);
    auto decide = [&](std::uint32_t step, std::uint32_t of) {
        const ValidationPoint& point = t.validation.back();
        t.abandoned =
            early_abort_reasons(point, std::uint64_t(step) * t.config.batch_size, p.gate, p.early_abort);
        if (!t.abandoned.empty()) {
            t.abandoned_at = step;
            return false;
        }
        t.fell_behind = falls_behind(point, larger, aim, p.target_stop, p.sizing);
        if (!t.fell_behind.empty()) return false;
        met_in_a_row = meets_target_with_margin(point, aim, p.target_stop) ? met_in_a_row + 1 : 0;
        if (p.target_stop.consecutive && met_in_a_row >= p.target_stop.consecutive && step < of) {
            t.target_met_at = step;
            return false;
        }
        return true;
    };
    t.stream = trainer::train_streamed(tr, *c.source, plan, [&](const trainer::Progress& pr) {
        if (!rays.validation.empty() && next_check <= checks &&
            std::uint64_t(pr.step) * checks >= std::uint64_t(next_check) * pr.steps) {
            ++next_check;
            const auto tv = Clock::now();
            t.validation.push_back(
                validation_point(pr.step, tr.export_model("{}"), rays.validation, run.threads));
            validation_seconds += seconds_since(tv);
            if (!decide(pr.step, pr.steps)) return false;
        }
        const double elapsed = seconds_since(t0);
        run.report({mesh.name, "train", pr.step, pr.steps, pr.loss,
                    pr.step ? elapsed / pr.step * (pr.steps - pr.step) : 0.0});
        return true;
    });
    const trainer::StreamedResult& st = t.stream;
    rec.stats["mean_occupied_per_ray"] = st.rays_reaching ? st.entry_points / double(st.rays_reaching) : 0.0;
    rec.stats["training_rays"] = rec.stats.value("training_rays", std::uint64_t(0)) + st.rays_drawn;
    rec.add_seconds("sample", st.generate_seconds);
    rec.add_seconds("prepare", st.prepare_seconds);
    rec.add_seconds("train", st.train.seconds - validation_seconds);
    rec.add_seconds("validate", validation_seconds);
    t.model = tr.export_model("{}");
    if (p.prune_inactive) {
        const auto tp = Clock::now();
        t.pruned = remove_inactive_neurons(t.model, active_neurons(t.model, rays.validation, run.threads));
        rec.add_seconds("prune", seconds_since(tp));
    }
    t.seconds = seconds_since(t0);
    return t;
}

json gate(const Run& run, const scene::Mesh& mesh, const format::ModelData& model, const Trained& t,
          const MeasureRays& rays, samples::Metrics& m, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "evaluate"});
    const format::Runtime rt = format::make_runtime(model);
    m = samples::held_out_metrics(rt, rays.held_out, run.threads, rays.held_out_geometric_normals);
    json metrics = {{"held_out_rays", rays.held_out.size()}, {"families", metrics_json(m)}};
    std::vector<std::string> reasons = gate_failures(m, run.preset.gate);
    if (t.stream.train.diverged) reasons.push_back(t.stream.train.message);
    for (const std::string& why : t.abandoned)
        reasons.push_back("training given up at step " + std::to_string(t.abandoned_at) + " of " +
                          std::to_string(t.config.steps) + ": " + why);
    json verdict = {{"passed", reasons.empty()}};
    if (!reasons.empty()) verdict["reasons"] = reasons;
    metrics["gate"] = verdict;
    rec.add_seconds("evaluate", seconds_since(t0));
    return metrics;
}

json candidate_json(const Option& o, const Trained& t) {
    const format::ModelDesc& d = o.model.desc;
    const json& p = o.metrics["families"]["pooled"];
    json j = {{"log2_table_size", d.log2_table_size},
              {"hidden_width", d.hidden_width},
              {"grid", grid_encoding_name(std::uint32_t(d.grid_encoding))},
              {"bytes", o.bytes},
              {"steps", t.stream.train.steps},
              {"steps_planned", t.config.steps},
              {"seconds", o.seconds},
              {"held_out",
               {{"visibility", p["visibility_accuracy"]},
                {"distance_pct", p["distance_error_median_pct"]},
                {"normal_deg", p["normal_error_median_deg"]}}},
              {"gate_passed", o.metrics["gate"]["passed"]},
              {"target_met", o.target_met},
              {"memory_rule_passed", o.memory_ok},
              {"outcome", o.outcome}};
    // The curve is the training's: recorded once, with the rung's fp16 export.
    if (d.grid_encoding == format::GridEncoding::fp16) j["validation"] = validation_json(t.validation);
    if (t.target_met_at) j["stopped"] = "the validation curve met the target";
    if (!t.abandoned.empty()) j["stopped"] = "given up: " + t.abandoned.front();
    if (!t.fell_behind.empty()) j["stopped"] = "given up: " + t.fell_behind;
    if (!t.pruned.empty()) j["pruned_neurons"] = t.pruned;
    return j;
}

Option measure_option(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                      format::ModelData model, const Trained& t, const MeasureRays& rays, MeshRecord& rec) {
    const auto t0 = Clock::now();
    Option o;
    o.rung = rung;
    o.model = std::move(model);
    o.metrics = gate(run, mesh, o.model, t, rays, o.held_out, rec);
    o.target_met =
        o.metrics["gate"]["passed"].get<bool>() && target_misses(o.held_out.pooled, run.opt.target).empty();
    auto bytes = format::serialize(o.model);
    o.bytes = bytes ? bytes->size() : 0;
    o.memory_ok = bytes && memory_rule_failure(run, c, o.bytes).empty();
    o.seconds = seconds_since(t0);
    return o;
}

Sized size_to_target(const Run& run, const scene::Mesh& mesh, Candidate& c, const voxelize::Occupancy& occ,
                     const MeasureRays& rays, MeshRecord& rec) {
    Sized sized;
    const Preset& p = run.preset;
    format::ModelDesc desc = c.desc;
    std::uint32_t budget = p.train.steps;  // steps left to all rungs
    for (;;) {
        const std::vector<ValidationPoint> larger =
            sized.rungs.empty() ? std::vector<ValidationPoint>{} : sized.rungs.back().validation;
        sized.rungs.push_back(train_rung(run, mesh, c, desc, occ, rays, budget, larger, rec));
        const std::size_t rung = sized.rungs.size() - 1;
        const Trained& t = sized.rungs[rung];
        const std::size_t first = sized.options.size();
        add_options(run, mesh, c, rung, rays, sized, rec);
        bool met = false, fits = false;  // some option meets the target / beats the BVH
        for (std::size_t i = first; i < sized.options.size(); ++i) {
            met = met || sized.options[i].target_met;
            fits = fits || sized.options[i].memory_ok;
        }
        const std::uint32_t used = t.stream.train.steps;
        budget -= std::min(budget, used);
        // A smaller rung is worth a try only after this one met the target (or could not
        // beat the BVH, the estimate having been too hopeful), and only with at least as many
        // steps as this one needed: a smaller model does not learn faster.
        if ((!met && fits) || !p.sizing.explore_smaller || budget < used ||
            desc.log2_table_size <= p.classify.min_log2_table_size)
            break;
        --desc.log2_table_size;
    }
    choose_option(sized);
    for (const Option& o : sized.options) sized.candidates.push_back(candidate_json(o, sized.rungs[o.rung]));
    return sized;
}

void add_options(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                 const MeasureRays& rays, Sized& sized, MeshRecord& rec) {
    const Trained& t = sized.rungs[rung];
    for (const format::GridEncoding e : rung_encodings(run.preset)) {
        format::ModelData model = t.model;
        if (e == format::GridEncoding::u8_affine) {
            auto quantized = format::quantize_model(t.model);
            if (!quantized) continue;  // cannot happen for a valid fp16 export; then fp16 only
            model = std::move(*quantized);
        }
        Option o = measure_option(run, mesh, c, rung, std::move(model), t, rays, rec);
        if (e == format::GridEncoding::fp16) o.seconds += t.seconds;  // the training is the fp16 option's
        sized.options.push_back(std::move(o));
    }
}

std::vector<format::GridEncoding> rung_encodings(const Preset& p) {
    if (p.sizing.quantize) return {format::GridEncoding::fp16, format::GridEncoding::u8_affine};
    return {format::GridEncoding::fp16};
}

void choose_option(Sized& sized) {
    const std::size_t n = sized.options.size();
    auto smaller = [&](std::size_t i) {
        return !sized.chosen || sized.options[i].bytes < sized.options[*sized.chosen].bytes;
    };
    auto passes = [&](const Option& o) { return o.memory_ok && o.metrics["gate"]["passed"].get<bool>(); };
    for (std::size_t i = 0; i < n; ++i)
        if (passes(sized.options[i]) && sized.options[i].target_met && smaller(i)) sized.chosen = i;
    if (sized.chosen) {
        sized.why = "the smallest of " + std::to_string(n) + " candidates that meets the target";
    } else {
        // No option meets the target: the most accurate model, the first rung's, ships if
        // it passes the gate, in its smallest encoding that does.
        for (std::size_t i = 0; i < n; ++i)
            if (sized.options[i].rung == 0 && passes(sized.options[i]) && smaller(i)) sized.chosen = i;
        if (sized.chosen) sized.why = "no candidate meets the target; the largest passes the gate";
    }
    for (std::size_t i = 0; i < n; ++i) {
        Option& o = sized.options[i];
        if (sized.chosen == i)
            o.outcome = "chosen: " + sized.why;
        else if (!o.metrics["gate"]["passed"].get<bool>())
            o.outcome = "fails the gate";
        else if (!o.memory_ok)
            o.outcome = "fails the memory rule";
        else if (o.target_met)
            o.outcome = "meets the target, but a smaller candidate does too";
        else
            o.outcome = "misses the target";
    }
}

json asset_metadata(const Run& run, const std::string& source, const scene::Mesh& mesh, const Candidate& c,
                    const Option& o, const Trained& t, const std::string& key) {
    const trainer::TrainConfig& cfg = t.config;
    const trainer::TrainResult& tres = t.stream.train;
    return {
        {"format", "lsnif-metadata/1"},
        {"tool", {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}, {"command", run.opt.command_line}}},
        {"object",
         {{"name", mesh.name},
          {"source", source},
          {"source_hash", scene::geometry_hash(mesh)},
          {"box_min", vec3(c.box.min)},
          {"box_max", vec3(c.box.max)},
          {"triangle_count", mesh.triangle_count()},
          {"vertex_count", mesh.vertex_count()},
          {"closed", c.source->is_closed()}}},
        {"model", model_json(o.model.desc)},
        {"training",
         {{"seed", run.opt.seed},
          {"arithmetic", arithmetic_id(run.opt.arithmetic)},
          {"steps", tres.steps},
          {"batch_size", cfg.batch_size},
          {"samples", tres.samples},
          {"rays", t.stream.rays_drawn},
          {"rays_per_round", t.stream.rays_per_round},
          {"window_rounds", std::max<std::uint32_t>(1, run.preset.train_window_chunks)},
          {"learning_rate_grid", cfg.grid_adam.lr},
          {"learning_rate_mlp", cfg.mlp_adam.lr},
          {"loss_weights",
           {{"visibility", cfg.loss.visibility},
            {"distance", cfg.loss.distance},
            {"normal", cfg.loss.normal},
            {"material", cfg.loss.material}}},
          {"final_loss", std::isfinite(tres.final_loss) ? tres.final_loss : 0.0f},
          {"preset", run.preset.name},
          {"divergence_rollbacks", tres.rollbacks}}},
        {"metrics", o.metrics},
        {"extensions", {{"lsnif_convert_key", key}}}};
}

format::Result<std::vector<std::uint8_t>> encode_asset(Option& o, const json& metadata) {
    o.model.metadata_json = metadata.dump(2);
    return format::serialize(o.model);
}

std::string option_summary(const Option& o) {
    const format::ModelDesc& d = o.model.desc;
    return "2^" + std::to_string(d.log2_table_size) + " rows, " +
           grid_encoding_name(std::uint32_t(d.grid_encoding)) + " grid, " + std::to_string(o.bytes) +
           " bytes";
}

std::string write_asset(const Run& run, const scene::Mesh& mesh, std::span<const std::uint8_t> bytes,
                        const fs::path& asset, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "write"});
    std::error_code ec;
    fs::create_directories(run.outdir, ec);
    const format::Error e = format::write_bytes_atomically(asset.string(), bytes);
    rec.add_seconds("write", seconds_since(t0));
    return e ? e.message : std::string();
}

std::string memory_rule_failure(const Run& run, const Candidate& c, std::uint64_t asset_bytes) {
    const double ratio = double(c.source->bvh_bytes()) / double(std::max<std::uint64_t>(1, asset_bytes));
    if (c.forced || ratio >= run.preset.classify.min_memory_ratio) return {};
    char why[200];
    std::snprintf(why, sizeof why,
                  "the chosen asset (%" PRIu64 " bytes) is only %.2fx smaller than the BVH (%.2fx needed)",
                  asset_bytes, ratio, run.preset.classify.min_memory_ratio);
    return why;
}

// The target as the manifest's settings record it.
json target_settings(const Target& t) {
    return {{"visibility", t.visibility}, {"distance_pct", t.distance_pct}, {"normal_deg", t.normal_deg}};
}

json target_json(const Target& t, const std::vector<std::string>& misses) {
    json j = target_settings(t);
    j["met"] = misses.empty();
    if (!misses.empty()) j["misses"] = misses;
    return j;
}

// The classification half of plan_mesh: the entry of a mesh that stays BVH, or null for
// a candidate (p.candidate and p.occupancy set).
json plan_decision(const Run& run, const scene::Mesh& mesh, Planned& p) {
    MeshRecord& rec = p.rec;
    if (run.forced(run.opt.force_simple, mesh.name))
        return rec.simple("forced simple by --simple " + mesh.name);
    const ClassifyRule& rule = run.preset.classify;
    const bool forced_complex = run.forced(run.opt.force_complex, mesh.name);
    if (mesh.triangle_count() < rule.min_triangles && !forced_complex)
        return rec.simple(std::to_string(mesh.triangle_count()) + " triangles < " +
                          std::to_string(rule.min_triangles) + ": a BVH is small and exact");
    p.candidate = classify(run, mesh, forced_complex, rec);
    if (!p.candidate) return rec.finish("simple");
    p.occupancy = voxelize_mesh(run, mesh, *p.candidate, rec);
    if (!p.occupancy || !worth_an_lsnif(run, mesh, *p.candidate, rec)) return rec.finish("simple");
    return nullptr;
}

Planned plan_mesh(const Run& run, const std::string& source, const scene::Mesh& mesh, MeshRecord rec,
                  std::vector<std::string>& warnings) {
    Planned p;
    p.mesh = &mesh;
    p.source = source;
    p.rec = std::move(rec);
    p.decided = plan_decision(run, mesh, p);
    if (p.candidate && p.candidate->source) {
        p.bvh_bytes = p.candidate->source->bvh_bytes();
    } else {
        std::string error;
        if (auto bytes = sampling::measure_bvh_bytes(view_of(mesh), error))
            p.bvh_bytes = *bytes;
        else
            warnings.push_back(source + ": mesh '" + mesh.name +
                               "': its BVH could not be measured (counted as 0 bytes): " + error);
    }
    if (p.decided.is_null()) {
        p.estimate = lsnif_bytes_estimate(p.candidate->desc, smallest_encoding(run.preset));
    } else {
        p.candidate.reset();  // a mesh that stays BVH needs no Embree scene any more
        p.occupancy.reset();
    }
    return p;
}

json convert_candidate(const Run& run, Planned& p, std::vector<std::string>& errors) {
    const scene::Mesh& mesh = *p.mesh;
    const std::string& source = p.source;
    MeshRecord& rec = p.rec;
    Candidate& c = *p.candidate;
    if (run.opt.dry_run) return rec.finish("complex");  // the plan only: no sampling, training or files

    const std::string key = asset_key(run, mesh, c.desc);
    const std::string file = hex16(fnv1a64(key)) + ".lsnif";
    const fs::path asset = run.outdir / file;
    if (auto previous = reusable_metrics(asset, key))
        return shipped(run, std::move(previous->metrics), previous->pooled, file, asset, true, rec);

    const MeasureRays rays = draw_measure_rays(run, mesh, c, rec);
    Sized sized = size_to_target(run, mesh, c, *p.occupancy, rays, rec);
    rec.entry["candidates"] = sized.candidates;
    // The chosen option, or the first rung's fp16 model when none may ship.
    Option& o = sized.options[sized.chosen.value_or(0)];
    const Trained& t = sized.rungs[o.rung];
    const json& metrics = o.metrics;
    rec.entry["validation"] = validation_json(t.validation);
    if (t.target_met_at)
        rec.entry["stopped_early"] = {{"step", t.target_met_at},
                                      {"steps", t.config.steps},
                                      {"reason", "validation curve met the target"}};
    if (!sized.chosen) return below_gate(metrics, !t.abandoned.empty(), rec);
    rec.reasons.push_back(option_summary(o) + ": " + sized.why);
    auto bytes = encode_asset(o, asset_metadata(run, source, mesh, c, o, t, key));
    if (!bytes) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + bytes.error().message);
        return rec.failed("the asset could not be encoded: " + bytes.error().message);
    }
    if (std::string why = memory_rule_failure(run, c, bytes->size()); !why.empty()) {
        rec.entry["metrics"] = metrics;
        return rec.simple(why);
    }
    if (std::string err = write_asset(run, mesh, *bytes, asset, rec); !err.empty()) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + err);
        return rec.failed("the asset could not be written: " + err);
    }
    return shipped(run, metrics, o.held_out.pooled, file, asset, false, rec);
}

// The gate's rules, for cache keys: they decide which option ships.
std::string gate_key(const Gate& g) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "gate%g,%g,%g,%g,%llu", g.min_visibility, g.min_family_visibility,
                  g.max_distance_median_pct, g.max_normal_median_deg, (unsigned long long)g.min_family_rays);
    return buf;
}

template <class T>
void hash_array(cache::Sha256& h, const std::vector<T>& v) {
    const std::uint64_t n = v.size();
    h.update({reinterpret_cast<const std::uint8_t*>(&n), sizeof n});
    h.update({reinterpret_cast<const std::uint8_t*>(v.data()), v.size() * sizeof(T)});
}

const std::string& cache_key(const Run& run, Planned& p) {
    static_assert(std::endian::native == std::endian::little, "cache keys hash little-endian arrays");
    if (!p.key.empty()) return p.key;
    const scene::Mesh& m = *p.mesh;
    cache::Sha256 h;
    h.update("lsnif-convert-result/2\n").update(tool_identity().digest).update("\n");
    h.update(asset_key(run, m, p.candidate->desc))
        .update("\n")
        .update(gate_key(run.preset.gate))
        .update("\n");
    h.update(p.forced() ? "forced\n" : "automatic\n")
        .update(p.source)
        .update("\n")
        .update(m.name)
        .update("\n");
    hash_array(h, m.positions);
    hash_array(h, m.indices);
    hash_array(h, m.normals);
    hash_array(h, m.triangle_materials);
    p.key = h.hex();
    return p.key;
}

// Fields of a manifest entry that belong to the scene the mesh is in, not to its result.
constexpr const char* kSceneFields[] = {"id", "name", "input", "source_mesh", "instances"};

// Why a stored record cannot be restored; empty when it can. The entry's own checksum
// already caught damage: this catches an entry written by a tool that stored something else.
std::string record_problem(const json& record, const cache::Entry& entry) {
    if (!record.is_object() || !record.contains("class") || !record["class"].is_string())
        return "the record is not a mesh entry";
    if (record.contains("lsnif")) {
        const std::string file = record["lsnif"].value("file", "");
        if (file.empty() || file.find('/') != std::string::npos || file.find("..") != std::string::npos)
            return "the record names no usable asset file";
        if (entry.payload.empty()) return "the record names an asset but the entry holds none";
    }
    return {};
}

// A stored result as this scene's entry: its asset written into OUTDIR, the scene's own
// fields put back. False (and `error`) when the asset cannot be written.
bool restore_cached(const Run& run, Planned& p, json& record, const cache::Entry& entry, std::string& error) {
    if (record.contains("lsnif")) {
        error = write_asset(run, *p.mesh, entry.payload,
                            run.outdir / record["lsnif"]["file"].get<std::string>(), p.rec);
        if (!error.empty()) return false;
        record["lsnif"]["reused"] = true;
    }
    for (const char* f : kSceneFields) record[f] = p.rec.entry[f];
    // This run's own stages (classification, voxelization): the stored record has no timings.
    if (!p.rec.timings.empty()) record["timings"] = p.rec.timings;
    // The stored measurement, so that every run this entry serves reports the same bytes.
    if (record.contains("stats") && record["stats"].contains("bvh_bytes"))
        p.bvh_bytes = record["stats"]["bvh_bytes"].get<std::uint64_t>();
    return true;
}

// The entry to store for a result just converted: the record without the scene's fields and
// without what differs between runs (timings: strip_run_dependent), the asset's bytes as
// written. So an entry is a function of its key: every machine and thread count stores the
// same bytes. Empty record when the asset cannot be read back.
cache::Entry entry_to_store(const Run& run, const json& result, std::string& problem) {
    cache::Entry entry;
    json record = result;
    for (const char* f : kSceneFields) record.erase(f);
    strip_run_dependent(record);
    if (record.contains("lsnif")) {
        auto bytes =
            format::read_file_bytes((run.outdir / record["lsnif"]["file"].get<std::string>()).string());
        if (!bytes) {
            problem = bytes.error().message;
            return {};
        }
        entry.payload = std::move(*bytes);
    }
    entry.record = record.dump();
    return entry;
}

json convert_cached(const Run& run, Planned& p, std::vector<std::string>& errors,
                    std::vector<std::string>& warnings, CacheCounts& counts) {
    if (!run.cache || run.opt.dry_run) return convert_candidate(run, p, errors);
    const std::string& key = cache_key(run, p);
    const cache::Lookup found = run.cache->get(key);
    if (found.status == cache::Status::corrupt) {
        ++counts.corrupt;
        warnings.push_back("corrupt cache entry, converting again: " + found.problem);
    } else if (found.status == cache::Status::hit) {
        json record = json::parse(found.entry.record, nullptr, false);
        std::string why = record_problem(record, found.entry);
        if (why.empty()) {
            if (!restore_cached(run, p, record, found.entry, why)) {
                errors.push_back(p.source + ": mesh '" + p.mesh->name + "': " + why);
                return p.rec.failed("the asset could not be written: " + why);
            }
            ++counts.hits;
            return record;
        }
        ++counts.corrupt;
        warnings.push_back("unusable cache entry, converting again: " + run.cache->entry_path(key).string() +
                           ": " + why);
    }
    const std::size_t errors_before = errors.size();
    json result = convert_candidate(run, p, errors);
    if (errors.size() != errors_before) return result;  // a failed write is not a result to keep
    std::string problem;
    const cache::Entry entry = entry_to_store(run, result, problem);
    auto stored = problem.empty() ? run.cache->put(key, entry) : cache::Result<void>(cache::Error{problem});
    if (!stored)
        warnings.push_back("not cached: " + stored.error().message);
    else
        ++counts.stored;
    return result;
}

// Estimated BVH bytes saved per asset byte: the budget's conversion order.
double saving_per_byte(const Planned& p) {
    return (double(p.bvh_bytes) - double(p.estimate)) / double(std::max<std::uint64_t>(1, p.estimate));
}

std::vector<std::size_t> conversion_order(const std::vector<Planned>& planned, bool budgeted) {
    std::vector<std::size_t> order;
    for (std::size_t i = 0; i < planned.size(); ++i)
        if (planned[i].decided.is_null()) order.push_back(i);
    if (budgeted)
        std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
            if (planned[a].forced() != planned[b].forced()) return planned[a].forced();
            return saving_per_byte(planned[a]) > saving_per_byte(planned[b]);
        });
    return order;
}

std::uint64_t bytes_after(const Planned& p, const json& entry) {
    if (entry.value("class", "") != "complex") return p.bvh_bytes;
    if (entry.contains("lsnif")) return entry["lsnif"]["bytes"].get<std::uint64_t>();
    return p.estimate;  // a dry run's plan
}

// The constants were measured on the 2-core reference machine (docs/pipeline.md "Shards").
// Training dominates and scales with steps x batch; drawing the rays scales with triangles.
// Integer arithmetic: every shard must compute the same estimate on any machine.
std::uint64_t estimated_cost_ms(const Run& run, const Planned& p) {
    const std::uint64_t samples = std::uint64_t(run.preset.train.steps) * run.preset.train.batch_size;
    return 4200 + samples * 255 / 100000 + std::uint64_t(p.mesh->triangle_count()) * 18 / 10000;
}

// Longest processing time first: within 4/3 of the best split of the estimated work. Ties
// go to the lowest shard index, so the split is a function of the inputs and settings alone.
std::vector<std::uint32_t> shard_owners(const Run& run, std::vector<Planned>& planned) {
    std::vector<std::uint32_t> owner(planned.size(), 0);
    if (run.opt.shard_count == 0) return owner;
    struct Job {
        std::uint64_t cost;
        std::string key;
        std::size_t index;
    };
    std::vector<Job> jobs;
    for (std::size_t i = 0; i < planned.size(); ++i)
        if (planned[i].decided.is_null())
            jobs.push_back({estimated_cost_ms(run, planned[i]), cache_key(run, planned[i]), i});
    std::sort(jobs.begin(), jobs.end(),
              [](const Job& a, const Job& b) { return a.cost != b.cost ? a.cost > b.cost : a.key < b.key; });
    std::vector<std::uint64_t> load(run.opt.shard_count, 0);
    for (const Job& j : jobs) {
        const auto least = std::size_t(std::min_element(load.begin(), load.end()) - load.begin());
        load[least] += j.cost;
        owner[j.index] = std::uint32_t(least) + 1;
    }
    return owner;
}

void strip_run_dependent(json& entry) {
    entry.erase("timings");
    if (entry.contains("lsnif")) entry["lsnif"].erase("reused");
    if (entry.contains("candidates"))
        for (json& c : entry["candidates"]) c.erase("seconds");
}

// Why a candidate stays BVH when the scene already fits the budget.
std::string fits_without_it(std::uint64_t total, std::uint64_t budget) {
    return "the scene fits the memory budget without it (" + std::to_string(total) + " of " +
           std::to_string(budget) + " bytes with this mesh as BVH)";
}

// What settling one candidate produced; kept apart per candidate so that concurrent jobs
// (--jobs) never share a vector, and merged in candidate order afterwards.
struct Settled {
    json entry;
    std::uint64_t after = 0;
    std::vector<std::string> errors, warnings;
    CacheCounts counts;
};

// Settles candidate `p` given the scene's memory `total` so far: recorded as another shard's,
// kept as BVH because the budget is met, or converted (through the cache). Reports "done".
Settled settle_candidate(const Run& run, Planned& p, std::uint32_t owner, std::uint64_t total) {
    Settled s;
    s.after = p.bvh_bytes;
    const std::uint64_t budget = run.opt.memory_budget;
    const std::vector<std::string>& only = run.opt.only_keys;
    if (run.opt.shard_count > 0 && owner != run.opt.shard_index) {
        s.entry = p.rec.simple("converted by shard " + std::to_string(owner) + " of " +
                               std::to_string(run.opt.shard_count));
    } else if (!only.empty() && std::find(only.begin(), only.end(), cache_key(run, p)) == only.end()) {
        s.entry = p.rec.deferred(kLeftToAnotherJob);
    } else if (budget > 0 && total <= budget && !p.forced()) {
        s.entry = p.rec.simple(fits_without_it(total, budget));
    } else {
        s.entry = convert_cached(run, p, s.errors, s.warnings, s.counts);
        s.after = bytes_after(p, s.entry);
    }
    if (run.opt.shard_count > 0) s.entry["shard"] = owner;
    if (run.opt.dry_run) {
        s.entry["cache_key"] = cache_key(run, p);
        s.entry["estimated_ms"] = estimated_cost_ms(run, p);
    }
    run.report({p.mesh->name, "done", 0, 0, 0, 0, &s.entry});
    p.candidate.reset();  // its Embree scene (the largest thing a candidate holds)
    p.occupancy.reset();
    return s;
}

// Settles the candidates in `order`: one after another when a budget decides each from the
// ones before it, otherwise up to run.opt.jobs at a time, each on its own thread (the
// conversions are independent; their results do not depend on which job ran them).
std::vector<Settled> settle_candidates(const Run& run, std::vector<Planned>& planned,
                                       const std::vector<std::size_t>& order,
                                       std::vector<std::uint64_t>& after) {
    std::vector<Settled> settled(planned.size());
    const std::vector<std::uint32_t> owner = shard_owners(run, planned);
    if (run.opt.memory_budget > 0 || run.opt.jobs <= 1 || order.size() <= 1) {
        for (std::size_t i : order) {
            const std::uint64_t total = std::accumulate(after.begin(), after.end(), std::uint64_t(0));
            settled[i] = settle_candidate(run, planned[i], owner[i], total);
            after[i] = settled[i].after;
        }
        return settled;
    }
    std::atomic<std::size_t> next{0};
    const auto jobs = std::uint32_t(std::min<std::size_t>(run.opt.jobs, order.size()));
    std::vector<std::thread> workers;
    std::mutex failed_mutex;
    std::exception_ptr failed;  // the first exception a job threw, rethrown once all joined
    auto work = [&] {
        try {
            for (std::size_t k; (k = next.fetch_add(1)) < order.size();) {
                const std::size_t i = order[k];
                settled[i] = settle_candidate(run, planned[i], owner[i], 0);
            }
        } catch (...) {
            std::lock_guard lock(failed_mutex);
            if (!failed) failed = std::current_exception();
            next = order.size();
        }
    };
    // Plain threads, not base::run_on_threads: each job's conversion uses the pool itself.
    for (std::uint32_t j = 1; j < jobs; ++j) workers.emplace_back(work);
    work();
    for (std::thread& w : workers) w.join();
    if (failed) std::rethrow_exception(failed);
    for (std::size_t i : order) after[i] = settled[i].after;
    return settled;
}

std::vector<json> convert_meshes(const Run& run, std::vector<Planned>& planned,
                                 std::vector<std::string>& errors, std::vector<std::string>& warnings,
                                 CacheCounts& counts) {
    std::vector<json> entries(planned.size());
    std::vector<std::uint64_t> after(planned.size());
    for (std::size_t i = 0; i < planned.size(); ++i) {
        after[i] = planned[i].bvh_bytes;
        if (planned[i].decided.is_null()) continue;
        entries[i] = planned[i].decided;
        run.report({planned[i].mesh->name, "done", 0, 0, 0, 0, &entries[i]});
    }
    const std::vector<std::size_t> order = conversion_order(planned, run.opt.memory_budget > 0);
    std::vector<Settled> settled = settle_candidates(run, planned, order, after);
    for (std::size_t i : order) {
        entries[i] = std::move(settled[i].entry);
        errors.insert(errors.end(), settled[i].errors.begin(), settled[i].errors.end());
        warnings.insert(warnings.end(), settled[i].warnings.begin(), settled[i].warnings.end());
        counts.hits += settled[i].counts.hits;
        counts.stored += settled[i].counts.stored;
        counts.corrupt += settled[i].counts.corrupt;
    }
    for (std::size_t i = 0; i < planned.size(); ++i) {
        json memory = {{"before", planned[i].bvh_bytes}, {"after", after[i]}};
        if (run.opt.dry_run && entries[i]["class"] == "complex") memory["estimated"] = true;
        entries[i]["memory"] = memory;
    }
    return entries;
}

// The cache keys of the candidates; call before convert_meshes, which releases them.
std::set<std::string> candidate_keys(const Run& run, std::vector<Planned>& planned) {
    std::set<std::string> keys;
    for (Planned& p : planned)
        if (p.decided.is_null()) keys.insert(cache_key(run, p));
    return keys;
}

// --object: every selected key names a candidate, and its result is in the cache.
void check_selected_stored(const Run& run, const cache::Store& store, const std::set<std::string>& keys,
                           std::vector<std::string>& errors) {
    for (const std::string& key : run.opt.only_keys) {
        std::error_code ec;
        if (!keys.count(key))
            errors.push_back("--object " + key +
                             ": no candidate of the inputs has this cache key (the inputs, the settings "
                             "or the build changed since it was planned: plan again)");
        else if (!fs::exists(store.entry_path(key), ec))
            errors.push_back("--object " + key + ": the result is not in the cache " + store.root().string());
    }
}

std::string unreachable_budget(const Run& run, const std::vector<Planned>& planned) {
    std::uint64_t fixed = 0;
    for (const Planned& p : planned)
        if (!p.decided.is_null()) fixed += p.bvh_bytes;
    if (run.opt.memory_budget == 0 || run.opt.memory_budget >= fixed) return {};
    return "--memory-budget " + std::to_string(run.opt.memory_budget) +
           " bytes is below the BVHs of the meshes that stay BVH in any case (" + std::to_string(fixed) +
           " bytes: fewer triangles than the classifier converts, --simple, or no memory benefit): no "
           "conversion can meet it";
}

json scene_memory(const Run& run, const std::vector<json>& entries) {
    std::uint64_t before = 0, after = 0;
    for (const json& e : entries) {
        before += e["memory"]["before"].get<std::uint64_t>();
        after += e["memory"]["after"].get<std::uint64_t>();
    }
    json j = {{"before", before}, {"after", after}};
    if (run.opt.memory_budget > 0) {
        j["budget"] = run.opt.memory_budget;
        j["fits"] = after <= run.opt.memory_budget;
    }
    if (run.opt.dry_run) j["estimated"] = true;
    return j;
}

json shipped(const Run& run, json metrics, const samples::FamilyMetrics& pooled, const std::string& file,
             const fs::path& asset, bool reused, MeshRecord& rec) {
    rec.entry["target"] = target_json(run.opt.target, target_misses(pooled, run.opt.target));
    rec.entry["metrics"] = std::move(metrics);
    std::error_code ec;
    rec.entry["lsnif"] = {{"file", file}, {"bytes", fs::file_size(asset, ec)}, {"reused", reused}};
    return rec.finish("complex");
}

json below_gate(const json& metrics, bool abandoned, MeshRecord& rec) {
    rec.entry["metrics"] = metrics;
    for (const auto& r : metrics["gate"].value("reasons", std::vector<std::string>{}))
        rec.reasons.push_back("gate: " + r);
    return rec.simple(abandoned ? "decided early from the validation curve: stays BVH"
                                : "held-out accuracy below the gate: stays BVH");
}

MeshRecord new_record(const scene::Scene& sc, std::size_t in, std::size_t k, std::size_t id) {
    const scene::Mesh& mesh = sc.meshes[k];
    std::size_t instances = 0;
    for (const auto& i : sc.instances) instances += i.mesh == k;
    MeshRecord rec;
    rec.entry = {{"id", id},
                 {"name", mesh.name},
                 {"input", in},
                 {"source_mesh", k},
                 {"triangles", mesh.triangle_count()},
                 {"vertices", mesh.vertex_count()},
                 {"geometry_hash", scene::geometry_hash(mesh)},
                 {"instances", instances}};
    return rec;
}

json manifest_json(const Run& run, const json& inputs, const json& meshes, const json& instances,
                   const json& memory) {
    json manifest = {
        {"format", kManifestFormat},
        {"tool",
         {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}, {"identity", tool_identity().digest}}},
        {"settings", settings_json(run.opt)},
        {"inputs", inputs},
        {"meshes", meshes},
        {"instances", instances},
        {"simple_geometry",
         {{"location", "inputs"},
          {"note", "simple meshes are read from their input file (meshes[].input, meshes[].source_mesh)"}}},
        {"scene_memory", memory}};
    return manifest;
}

}  // namespace stages

using namespace stages;

namespace {

// Why the options split work that a memory budget must decide in order; empty when they do not.
std::string budget_conflict(const ConvertOptions& opt) {
    if (opt.memory_budget == 0) return {};
    const char* other = opt.shard_count > 0 ? "--shard" : opt.jobs > 1 ? "--jobs" : nullptr;
    if (!other) return {};
    return std::string(other) +
           " and --memory-budget cannot be combined: the budget decides each conversion from the ones "
           "before it";
}

}  // namespace

std::string arithmetic_id(Arithmetic a) {
    if (a == Arithmetic::machine &&
        trainer::resolve_precision(trainer::MlpPrecision::automatic) == trainer::MlpPrecision::bf16)
        return "machine-" + trainer::mlp_arithmetic(trainer::MlpPrecision::automatic);
    return "canonical-" + std::to_string(kCanonicalArithmeticVersion);
}

bool parse_arithmetic(const std::string& text, Arithmetic& out) {
    if (text == "canonical")
        out = Arithmetic::canonical;
    else if (text == "machine")
        out = Arithmetic::machine;
    else
        return false;
    return true;
}

std::uint32_t threads_per_job(const ConvertOptions& opt) {
    return std::max(1u, base::resolve_threads(opt.threads) / std::max(1u, opt.jobs));
}

ConvertResult convert(const ConvertOptions& opt, const ConvertProgress& progress) {
    ConvertResult res;
    Preset preset;
    std::string error;
    if (!resolve_preset(opt, preset, error)) {
        res.errors.push_back(error);
        return res;
    }
    std::shared_ptr<const cache::Store> store;
    if (!opt.cache_dir.empty() && !opt.dry_run) {
        auto opened = cache::Store::open(opt.cache_dir);
        if (!opened) {
            res.errors.push_back(opened.error().message);
            return res;
        }
        store = std::make_shared<const cache::Store>(std::move(*opened));
    }
    if (std::string why = budget_conflict(opt); !why.empty()) {
        res.errors.push_back(why);
        res.usage_error = true;
        return res;  // nothing imported, trained or written
    }
    // Concurrent jobs report from their own threads: one at a time reaches the caller.
    auto progress_mutex = std::make_shared<std::mutex>();
    const ConvertProgress serialized =
        !progress || opt.jobs <= 1 ? progress
                                   : ConvertProgress([progress, progress_mutex](const ProgressEvent& e) {
                                         std::lock_guard lock(*progress_mutex);
                                         progress(e);
                                     });
    const Run run{opt, std::move(preset), threads_per_job(opt), opt.outdir, serialized, store};
    json inputs = json::array(), instances = json::array();
    std::deque<scene::Scene> scenes;  // every input stays imported: candidates borrow their meshes
    std::vector<GltfSource> sources;  // per input, for scene.gltf
    std::vector<Planned> planned;
    std::size_t ok_inputs = 0;
    double import_seconds = 0;
    for (std::size_t in = 0; in < opt.inputs.size(); ++in) {
        const std::string& path = opt.inputs[in];
        run.report({path, "import"});
        const auto t0 = Clock::now();
        auto imported = scene::import_scene(path);
        import_seconds += seconds_since(t0);
        json in_json = {{"path", manifest_relative_path(path, run.outdir)}, {"given", path}};
        sources.push_back({path, nullptr});
        if (!imported.ok()) {
            res.errors.push_back(imported.error);
            in_json["status"] = "error";
            in_json["error"] = imported.error;
            inputs.push_back(in_json);
            continue;
        }
        ++ok_inputs;
        const scene::Scene& sc = scenes.emplace_back(std::move(imported.scene));
        sources.back().scene = &sc;
        in_json["status"] = "ok";
        if (!sc.warnings.empty()) {
            in_json["warnings"] = sc.warnings;
            for (const auto& w : sc.warnings) res.warnings.push_back(path + ": " + w);
        }
        inputs.push_back(in_json);
        const std::size_t first_id = planned.size();
        for (std::size_t k = 0; k < sc.meshes.size(); ++k)
            planned.push_back(
                plan_mesh(run, path, sc.meshes[k], new_record(sc, in, k, planned.size()), res.warnings));
        for (const auto& i : sc.instances)
            instances.push_back({{"mesh", first_id + i.mesh},
                                 {"name", i.node_name},
                                 {"transform", std::vector<float>(i.transform.begin(), i.transform.end())}});
    }
    if (std::string why = unreachable_budget(run, planned); !why.empty()) {
        res.errors.push_back(why);
        res.usage_error = true;
        return res;  // nothing trained, nothing written
    }
    CacheCounts cache_counts;
    const std::set<std::string> keys =
        opt.only_keys.empty() ? std::set<std::string>() : candidate_keys(run, planned);
    const std::vector<json> entries = convert_meshes(run, planned, res.errors, res.warnings, cache_counts);
    const json meshes = entries, memory = scene_memory(run, entries);
    if (memory.contains("fits") && !memory["fits"].get<bool>())
        res.warnings.push_back("the scene needs " + std::to_string(memory["after"].get<std::uint64_t>()) +
                               " bytes, over the memory budget of " + std::to_string(opt.memory_budget) +
                               " bytes, with every candidate that passed converted");

    res.report = {{"inputs", inputs},       {"meshes", meshes},     {"instances", instances.size()},
                  {"scene_memory", memory}, {"errors", res.errors}, {"warnings", res.warnings}};
    res.report["timings"] = {{"import", import_seconds}};  // per-mesh stages are in meshes[].timings
    if (opt.dry_run) res.report["dry_run"] = true;
    if (store)
        res.report["cache"] = {{"directory", opt.cache_dir},
                               {"hits", cache_counts.hits},
                               {"stored", cache_counts.stored},
                               {"corrupt", cache_counts.corrupt}};
    if (ok_inputs == 0 || opt.dry_run) return res;  // nothing converted, or a plan: leave OUTDIR untouched

    if (!opt.only_keys.empty()) {  // one job's share: its cache entries, no manifest
        if (store) check_selected_stored(run, *store, keys, res.errors);
        return res;
    }
    json manifest_meshes = meshes;
    if (opt.reproducible_manifest)
        for (json& m : manifest_meshes) strip_run_dependent(m);
    res.manifest = manifest_json(run, inputs, manifest_meshes, instances, memory);
    if (opt.shard_count > 0) res.manifest["shard"] = {{"index", opt.shard_index}, {"count", opt.shard_count}};
    if (std::string e = write_manifest(run.outdir, res.manifest); !e.empty()) res.errors.push_back(e);
    res.report["manifest"] = (run.outdir / "manifest.json").string();
    if (opt.write_gltf) {
        if (std::string e = write_scene_gltf(run.outdir, sources, res.manifest); !e.empty())
            res.errors.push_back(e);
        else
            res.report["gltf"] = (run.outdir / "scene.gltf").string();
    }
    return res;
}

// "812 B", "406.2 KiB", "84.1 MiB", "1.20 GiB": a byte count as the text report shows it.
std::string human_bytes(std::uint64_t bytes) {
    char buf[32];
    if (bytes < 1024)
        std::snprintf(buf, sizeof buf, "%" PRIu64 " B", bytes);
    else if (bytes < (1u << 20))
        std::snprintf(buf, sizeof buf, "%.1f KiB", double(bytes) / 1024);
    else if (bytes < (1u << 30))
        std::snprintf(buf, sizeof buf, "%.1f MiB", double(bytes) / (1u << 20));
    else
        std::snprintf(buf, sizeof buf, "%.2f GiB", double(bytes) / (1u << 30));
    return buf;
}

// "BVH 84.1 MiB -> 406.2 KiB": a mesh's or the scene's memory before and after conversion.
std::string memory_text(const json& memory) {
    const std::uint64_t before = memory["before"].get<std::uint64_t>(),
                        after = memory["after"].get<std::uint64_t>();
    return human_bytes(before) + " -> " + human_bytes(after) +
           (memory.value("estimated", false) ? " (est.)" : "");
}

std::string convert_text(const ConvertResult& r) {
    std::string s;
    char buf[512];
    if (!r.report.contains("meshes")) return s;
    for (const json& m : r.report["meshes"]) {
        std::snprintf(buf, sizeof buf, "%-8s %-24s %9" PRIu64 " tris  x%-3" PRIu64 "  %-28s",
                      m["class"].get<std::string>().c_str(),
                      m["name"].get<std::string>().substr(0, 24).c_str(), m["triangles"].get<std::uint64_t>(),
                      m.value("instances", std::uint64_t(0)),
                      m.contains("memory") ? memory_text(m["memory"]).c_str() : "");
        s += buf;
        if (m.contains("lsnif")) {
            const json& p = m["metrics"]["families"]["pooled"];
            std::snprintf(
                buf, sizeof buf, "  %s  vis %.2f%%  dist %.3f%%  normal %.1f deg%s",
                m["lsnif"]["file"].get<std::string>().c_str(), 100 * p["visibility_accuracy"].get<double>(),
                p["distance_error_median_pct"].get<double>(), p["normal_error_median_deg"].get<double>(),
                m["lsnif"]["reused"].get<bool>() ? " (reused)" : "");
            s += buf;
            if (m.contains("target") && !m["target"]["met"].get<bool>())
                s +=
                    "\n           target missed, gate passed: " + m["target"]["misses"][0].get<std::string>();
            if (m.contains("stopped_early")) {
                std::snprintf(buf, sizeof buf,
                              "\n           trained %u of %u steps: the validation curve met the target",
                              m["stopped_early"]["step"].get<unsigned>(),
                              m["stopped_early"]["steps"].get<unsigned>());
                s += buf;
            }
            const json& fam = m["metrics"]["families"];
            for (const char* f : {"outside", "surface", "interior"}) {
                std::snprintf(buf, sizeof buf,
                              "\n           %-8s vis %.2f%%  dist %.3f%% (p95 %.2f%%)  normal %.1f deg (p95 "
                              "%.1f)  culled %.0f%%",
                              f, 100 * fam[f]["visibility_accuracy"].get<double>(),
                              fam[f]["distance_error_median_pct"].get<double>(),
                              fam[f]["distance_error_p95_pct"].get<double>(),
                              fam[f]["normal_error_median_deg"].get<double>(),
                              fam[f]["normal_error_p95_deg"].get<double>(),
                              100 * fam[f]["culled_fraction"].get<double>());
                s += buf;
            }
        } else if (!m["reasons"].empty()) {
            s += "  " + m["reasons"].back().get<std::string>();
        }
        s += "\n";
    }
    std::snprintf(buf, sizeof buf, "%zu meshes, %" PRIu64 " instances\n", r.report["meshes"].size(),
                  r.report["instances"].get<std::uint64_t>());
    s += buf;
    if (r.report.contains("scene_memory")) {
        const json& mem = r.report["scene_memory"];
        s += "scene memory (each mesh once): " + memory_text(mem);
        if (mem.contains("budget"))
            s += std::string(", budget ") + human_bytes(mem["budget"].get<std::uint64_t>()) +
                 (mem["fits"].get<bool>() ? ": fits" : ": over budget");
        s += "\n";
    }
    if (r.report.contains("manifest")) s += "manifest: " + r.report["manifest"].get<std::string>() + "\n";
    if (r.report.contains("gltf")) s += "glTF: " + r.report["gltf"].get<std::string>() + "\n";
    if (r.report.value("dry_run", false)) s += "dry run: nothing written\n";
    return s;
}

}  // namespace lsnif::converter
