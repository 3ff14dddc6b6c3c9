// The decision rules over typed metrics: the gate, the target, giving up early, stopping at
// the target, a smaller rung falling behind (convert.hpp has the contracts).
#include <lsnif/converter/convert.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

namespace {

std::string gate_reason(const char* what, double value, const char* op, double limit, const char* unit) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "%s %.4g%s %s gate %.4g%s", what, value, unit, op, limit, unit);
    return buf;
}

}  // namespace

std::vector<std::string> gate_failures(const samples::Metrics& m, const Gate& g) {
    std::vector<std::string> fails;
    if (m.pooled.visibility_accuracy < g.min_visibility)
        fails.push_back(gate_reason("visibility accuracy", 100 * m.pooled.visibility_accuracy, "<",
                                    100 * g.min_visibility, "%"));
    for (int f = 0; f < samples::kFamilyCount; ++f)
        if (m.family[f].rays < g.min_family_rays)
            fails.push_back(std::string(samples::family_name(samples::Family(f))) +
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

// Why `flip` misses `limit` ("image error FLIP 0.083 > gate 0.066"), or empty when it does not.
std::string flip_miss(std::optional<double> flip, double limit, const char* what) {
    char buf[120];
    if (!flip) {
        std::snprintf(buf, sizeof buf, "image error not measured (the visual check is off)");
        return buf;
    }
    if (*flip <= limit) return {};
    std::snprintf(buf, sizeof buf, "image error FLIP %.3g over the object's pixels > %s %.3g", *flip, what,
                  limit);
    return buf;
}

}  // namespace

GateVerdict gate_verdict(const samples::Metrics& m, std::optional<double> flip,
                         std::vector<std::string> training_failures, const Gate& g) {
    GateVerdict v;
    const std::vector<std::string> rays = gate_failures(m, g);
    const std::string image = flip_miss(flip, g.max_flip, "gate");
    const bool rays_pass = rays.empty(), image_pass = image.empty();
    const bool by_rays = g.accept != Acceptance::images && rays_pass;
    const bool by_images = g.accept != Acceptance::rays && image_pass;
    v.passed = training_failures.empty() && (by_rays || by_images);
    if (v.passed) {
        v.by = by_rays && by_images ? GatePass::both : by_rays ? GatePass::rays : GatePass::images;
        if (*v.by == GatePass::images) {
            v.rays_failed = rays;
            v.above_calibrated = flip && *flip > Gate::kCalibratedMaxFlip;
        }
        return v;
    }
    if (g.accept != Acceptance::images) v.reasons = rays;
    if (g.accept != Acceptance::rays && !image.empty()) v.reasons.push_back(image);
    for (std::string& why : training_failures) v.reasons.push_back(std::move(why));
    return v;
}

std::vector<std::string> target_misses(const samples::FamilyMetrics& p, std::optional<double> flip,
                                       const Target& t, Acceptance accept) {
    std::vector<std::string> misses;
    char buf[160];
    const double vis = p.visibility_accuracy, dist = p.distance_median_pct, normal = p.normal_median_deg;
    if (accept != Acceptance::images && vis < t.visibility) {
        std::snprintf(buf, sizeof buf, "visibility %.2f %% < target %.2f %%", 100 * vis, 100 * t.visibility);
        misses.push_back(buf);
    }
    if (accept != Acceptance::images && dist > t.distance_pct) {
        std::snprintf(buf, sizeof buf, "median distance error %.3g %% > target %.3g %%", dist,
                      t.distance_pct);
        misses.push_back(buf);
    }
    if (accept != Acceptance::images && normal > t.normal_deg) {
        std::snprintf(buf, sizeof buf, "median normal error %.3g deg > target %.3g deg", normal,
                      t.normal_deg);
        misses.push_back(buf);
    }
    if (flip || accept == Acceptance::images)
        if (std::string miss = flip_miss(flip, t.flip, "target"); !miss.empty()) misses.push_back(miss);
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

std::string finer_grid_reason(const ValidationPoint& point, std::uint64_t samples, const Target& aim,
                              const EarlyAbort& abort, const Sizing& rule) {
    if (samples < abort.min_samples || point.visibility + rule.finer_grid_headroom >= aim.visibility)
        return {};
    char buf[200];
    std::snprintf(buf, sizeof buf,
                  "validation visibility %.1f %% at step %u cannot reach the target's %.1f %%",
                  100 * point.visibility, point.step, 100 * aim.visibility);
    return buf;
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

}  // namespace lsnif::converter
