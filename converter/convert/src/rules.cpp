// The decision rules over typed metrics: the gate, the target, giving up early, stopping at
// the target, a smaller rung falling behind (convert.hpp has the contracts).
#include <lsnif/converter/convert.hpp>
#include "convert_stages.hpp"

#include <lsnif/base/text.hpp>

namespace lsnif::converter {

using base::printed;

using nlohmann::json;
using namespace stages;

namespace {

// A gate line: "visibility accuracy 82.73% < gate 95%".
std::string gate_line(const std::string& what, double value, const char* op, double limit, const char* unit) {
    return printed("%s %.4g%s %s gate %.4g%s", what.c_str(), value, unit, op, limit, unit);
}

// A miss of `measure` against `bound`: measured `value`, allowed `limit`.
RuleMiss miss(Measure measure, Bound bound, double value = 0, double limit = 0,
              std::optional<samples::Family> family = std::nullopt, std::uint32_t step = 0) {
    RuleMiss m;
    m.measure = measure;
    m.bound = bound;
    m.value = value;
    m.limit = limit;
    m.family = family;
    m.step = step;
    return m;
}

std::string family_prefix(const RuleMiss& m) {
    return m.family ? std::string(samples::family_name(*m.family)) + " " : std::string();
}

std::string describe_gate(const RuleMiss& m) {
    switch (m.measure) {
        case Measure::visibility:
            return gate_line(m.family ? family_prefix(m) + "visibility" : "visibility accuracy",
                             100 * m.value, "<", 100 * m.limit, "%");
        case Measure::family_rays:
            return family_prefix(m) + "rays reaching the network: " + std::to_string(std::uint64_t(m.value)) +
                   " < " + std::to_string(std::uint64_t(m.limit)) + " (too few to measure)";
        case Measure::distance:
            return gate_line("median distance error", m.value, ">", m.limit, "% of diagonal");
        case Measure::normal: return gate_line("median normal error", m.value, ">", m.limit, " deg");
        default: break;
    }
    return {};
}

std::string describe_target(const RuleMiss& m) {
    switch (m.measure) {
        case Measure::visibility:
            return printed("visibility %.2f %% < target %.2f %%", 100 * m.value, 100 * m.limit);
        case Measure::distance:
            return printed("median distance error %.3g %% > target %.3g %%", m.value, m.limit);
        case Measure::normal:
            return printed("median normal error %.3g deg > target %.3g deg", m.value, m.limit);
        default: break;
    }
    return {};
}

std::string describe_curve(const RuleMiss& m) {
    if (m.bound == Bound::larger_rung)
        return printed(
            "validation visibility %.2f %% at step %u; the larger model gained %.2f points after that "
            "step, short of the %.2f %% needed",
            100 * m.value, m.step, 100 * m.larger_gain, 100 * m.limit);
    if (m.bound == Bound::target_out_of_reach)
        return printed("validation visibility %.1f %% at step %u cannot reach the target's %.1f %%",
                       100 * m.value, m.step, 100 * m.limit);
    switch (m.measure) {
        case Measure::visibility:
            return printed("validation visibility %.1f %% cannot reach the gate's %.1f %%", 100 * m.value,
                           100 * m.limit);
        case Measure::normal:
            return printed("validation normal error %.1f deg cannot reach the gate's %.1f deg", m.value,
                           m.limit);
        case Measure::distance:
            return printed("validation distance error %.2f %% cannot reach the gate's %.2f %%", m.value,
                           m.limit);
        default: break;
    }
    return {};
}

}  // namespace

std::string describe(const RuleMiss& m) {
    if (m.measure == Measure::image_unmeasured) return "image error not measured (the visual check is off)";
    if (m.measure == Measure::image)
        return printed("image error FLIP %.3g over the object's pixels > %s %.3g", m.value,
                       m.bound == Bound::target ? "target" : "gate", m.limit);
    switch (m.bound) {
        case Bound::gate: return describe_gate(m);
        case Bound::target: return describe_target(m);
        case Bound::gate_out_of_reach:
        case Bound::target_out_of_reach:
        case Bound::larger_rung: return describe_curve(m);
    }
    return {};
}

std::vector<std::string> describe(std::span<const RuleMiss> misses) {
    std::vector<std::string> lines;
    for (const RuleMiss& m : misses) lines.push_back(describe(m));
    return lines;
}

std::vector<RuleMiss> gate_failures(const samples::Metrics& m, const Gate& g) {
    std::vector<RuleMiss> fails;
    const Bound b = Bound::gate;
    if (m.pooled.visibility_accuracy < g.min_visibility)
        fails.push_back(miss(Measure::visibility, b, m.pooled.visibility_accuracy, g.min_visibility));
    for (int f = 0; f < samples::kFamilyCount; ++f)
        if (m.family[f].rays < g.min_family_rays)
            fails.push_back(miss(Measure::family_rays, b, double(m.family[f].rays), double(g.min_family_rays),
                                 samples::Family(f)));
    for (int f = 0; f < samples::kFamilyCount; ++f)
        if (m.family[f].rays && m.family[f].visibility_accuracy < g.min_family_visibility)
            fails.push_back(miss(Measure::visibility, b, m.family[f].visibility_accuracy,
                                 g.min_family_visibility, samples::Family(f)));
    if (m.pooled.distance_median_pct > g.max_distance_median_pct)
        fails.push_back(miss(Measure::distance, b, m.pooled.distance_median_pct, g.max_distance_median_pct));
    if (m.pooled.normal_median_deg > g.max_normal_median_deg)
        fails.push_back(miss(Measure::normal, b, m.pooled.normal_median_deg, g.max_normal_median_deg));
    return fails;
}

const char* bvh_yardstick_name(BvhYardstick y) {
    return y == BvhYardstick::compressed ? "compressed" : "embree";
}

bool parse_bvh_yardstick(const std::string& text, BvhYardstick& out) {
    for (const BvhYardstick y : {BvhYardstick::embree, BvhYardstick::compressed})
        if (text == bvh_yardstick_name(y)) return out = y, true;
    return false;
}

const char* acceptance_name(Acceptance a) {
    switch (a) {
        case Acceptance::rays: return "rays";
        case Acceptance::images: return "images";
        case Acceptance::either: return "either";
    }
    return "either";
}

bool parse_acceptance(const std::string& text, Acceptance& out) {
    for (const Acceptance a : {Acceptance::rays, Acceptance::images, Acceptance::either})
        if (text == acceptance_name(a)) return out = a, true;
    return false;
}

namespace {

// The image rule against `limit` (`bound`: gate or target): none when `flip` meets it.
std::optional<RuleMiss> flip_miss(std::optional<double> flip, double limit, Bound bound) {
    if (!flip) return miss(Measure::image_unmeasured, bound);
    if (*flip <= limit) return std::nullopt;
    return miss(Measure::image, bound, *flip, limit);
}

}  // namespace

GateVerdict gate_verdict(const samples::Metrics& m, std::optional<double> flip,
                         std::vector<std::string> training_failures, const Gate& g) {
    GateVerdict v;
    const std::vector<RuleMiss> rays = gate_failures(m, g);
    const std::optional<RuleMiss> image = flip_miss(flip, g.max_flip, Bound::gate);
    const bool rays_pass = rays.empty(), image_pass = !image;
    const bool by_rays = g.accept != Acceptance::images && rays_pass;
    const bool by_images = g.accept != Acceptance::rays && image_pass;
    v.passed = training_failures.empty() && (by_rays || by_images);
    if (v.passed) {
        v.by = by_rays && by_images ? GatePass::both : by_rays ? GatePass::rays : GatePass::images;
        if (*v.by == GatePass::images) {
            v.rays_failed = describe(rays);
            v.above_calibrated = flip && *flip > Gate::kCalibratedMaxFlip;
        }
        return v;
    }
    if (g.accept != Acceptance::images) v.reasons = describe(rays);
    if (g.accept != Acceptance::rays && image) v.reasons.push_back(describe(*image));
    for (std::string& why : training_failures) v.reasons.push_back(std::move(why));
    return v;
}

std::vector<RuleMiss> target_misses(const samples::FamilyMetrics& p, std::optional<double> flip,
                                    const Target& t, Acceptance accept) {
    std::vector<RuleMiss> misses;
    const Bound b = Bound::target;
    const bool rays = accept != Acceptance::images;
    if (rays && p.visibility_accuracy < t.visibility)
        misses.push_back(miss(Measure::visibility, b, p.visibility_accuracy, t.visibility));
    if (rays && p.distance_median_pct > t.distance_pct)
        misses.push_back(miss(Measure::distance, b, p.distance_median_pct, t.distance_pct));
    if (rays && p.normal_median_deg > t.normal_deg)
        misses.push_back(miss(Measure::normal, b, p.normal_median_deg, t.normal_deg));
    if (flip || accept == Acceptance::images)
        if (std::optional<RuleMiss> miss = flip_miss(flip, t.flip, b)) misses.push_back(*miss);
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

std::vector<RuleMiss> early_abort_reasons(const ValidationPoint& point, std::uint64_t samples, const Gate& g,
                                          const EarlyAbort& rule) {
    std::vector<RuleMiss> why;
    if (samples < rule.min_samples) return why;
    const Bound b = Bound::gate_out_of_reach;
    if (point.visibility + rule.visibility_headroom < g.min_visibility)
        why.push_back(
            miss(Measure::visibility, b, point.visibility, g.min_visibility, std::nullopt, point.step));
    if (point.normal_deg - rule.normal_headroom_deg > g.max_normal_median_deg)
        why.push_back(
            {Measure::normal, b, point.normal_deg, g.max_normal_median_deg, std::nullopt, point.step});
    if (point.distance_pct * rule.distance_factor > g.max_distance_median_pct)
        why.push_back(
            {Measure::distance, b, point.distance_pct, g.max_distance_median_pct, std::nullopt, point.step});
    return why;
}

std::optional<RuleMiss> finer_grid_reason(const ValidationPoint& point, std::uint64_t samples,
                                          const Target& aim, const EarlyAbort& abort, const Sizing& rule) {
    if (samples < abort.min_samples || point.visibility + rule.finer_grid_headroom >= aim.visibility)
        return std::nullopt;
    return miss(Measure::visibility, Bound::target_out_of_reach, point.visibility, aim.visibility,
                std::nullopt, point.step);
}

Target effective_target(const Target& t, const Gate& g) {
    return {std::max(t.visibility, g.min_visibility), std::min(t.distance_pct, g.max_distance_median_pct),
            std::min(t.normal_deg, g.max_normal_median_deg), std::min(t.flip, g.max_flip)};
}

bool meets_target_with_margin(const ValidationPoint& point, const Target& t, const TargetStop& rule) {
    return point.visibility >= t.visibility + rule.visibility_margin &&
           point.distance_pct <= t.distance_pct * rule.distance_factor &&
           point.normal_deg <= t.normal_deg - rule.normal_margin_deg;
}

bool near_target(const samples::FamilyMetrics& pooled, const Target& t, const Sizing& rule) {
    return pooled.visibility_accuracy >= t.visibility - rule.climb_visibility &&
           pooled.distance_median_pct <= t.distance_pct * rule.climb_distance_factor &&
           pooled.normal_median_deg <= t.normal_deg + rule.climb_normal_deg;
}

std::optional<RuleMiss> falls_behind(const ValidationPoint& point, std::span<const ValidationPoint> larger,
                                     const Target& target, const TargetStop& stop, const Sizing& rule) {
    // The larger rung's visibility at the last check at or before the point's step, and the
    // most it gained from there on.
    const std::uint32_t step = point.step;
    const ValidationPoint* at = nullptr;
    for (const ValidationPoint& q : larger)
        if (q.step <= step) at = &q;
    if (!at || larger.back().step < step) return std::nullopt;
    double best = 0;
    for (const ValidationPoint& q : larger)
        if (q.step >= at->step) best = std::max(best, q.visibility);
    const double gain = best - at->visibility;
    const double vis = point.visibility, needed = target.visibility + stop.visibility_margin;
    if (vis + gain + rule.curve_slack >= needed) return std::nullopt;
    RuleMiss behind = miss(Measure::visibility, Bound::larger_rung, vis, needed, std::nullopt, step);
    behind.larger_gain = gain;
    return behind;
}

}  // namespace lsnif::converter
