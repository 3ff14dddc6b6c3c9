// The rules a conversion decides by, over typed metrics: which meshes are candidates
// (ClassifyRule), what may ship (Gate), what a user asks for (Target), giving up and stopping
// during training (EarlyAbort, TargetStop) and the sizing ladder (Sizing), with the functions
// that apply them (converter/convert/src/rules.cpp). docs/architecture.md §3 and docs/model.md
// "Validation curve and deciding early" explain them.
#pragma once

#include <lsnif/samples/held_out.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace lsnif::converter {

// The BVH an asset's memory is compared with (--bvh-yardstick; docs/convert.md "Memory").
enum class BvhYardstick : std::uint8_t {
    // Embree's BVH of the mesh as built (its memory monitor over the commit: nodes and leaf
    // triangles): what a CPU renderer tracing through Embree holds.
    embree,
    // An 8-wide compressed BVH as GPU renderers hold (sampling::CompressedBvh: 80 bytes per
    // inner node, leaf triangles not counted): the smallest BVH a renderer could hold, a
    // lower bound, and the yardstick of the LSNIF paper's memory figures.
    compressed,
};
// "embree", "compressed" (the --bvh-yardstick values); and back, false for anything else.
const char* bvh_yardstick_name(BvhYardstick y);
bool parse_bvh_yardstick(const std::string& text, BvhYardstick& out);

// Classification thresholds (docs/convert.md "Which meshes convert").
//
// Model sizing ("never model more than a scene needs"): the preset's hash-table size
// 2^log2_table_size is the largest a mesh gets. It is halved while the asset's resident
// bytes (what a renderer holds once it is open: format::resident_bytes) would not beat the
// yardstick's BVH by min_memory_ratio, down to 2^min_log2_table_size; a mesh that still does
// not benefit stays BVH. `--complex NAME` skips this sizing and the memory rule: the mesh
// starts at the preset's model, and only the target (Sizing) makes it smaller.
struct ClassifyRule {
    std::uint64_t min_triangles = 2000;  // fewer: the BVH is tiny and exact; keep it
    // An approximation must at least halve the memory of what it replaces: a saving of a few
    // tens of percent is not worth the share of wrong visibility every asset brings
    // (docs/investigations/sizing.md, the 2CylinderEngine's small parts).
    double min_memory_ratio = 2.0;  // the yardstick's BVH bytes >= this x the asset's resident bytes
    BvhYardstick yardstick = BvhYardstick::embree;
    std::uint32_t min_log2_table_size = 15;  // smallest table sizing may choose (2^15 rows)
};

// What may ship an asset (docs/model.md "Judged by how it looks"): its ray metrics passing
// the gate's ray rules, its image error (the visual check's FLIP) within Gate::max_flip, or
// either of the two.
enum class Acceptance : std::uint8_t { rays, images, either };
// "rays", "images", "either" (the --accept values); and back, false for anything else.
const char* acceptance_name(Acceptance a);
bool parse_acceptance(const std::string& text, Acceptance& out);

// The accuracy an asset must reach to ship (docs/architecture.md §3 "Gate"), measured on the
// decision rays (never the held-out rays, which only report).
struct Gate {
    double min_visibility = 0.95;          // pooled visibility accuracy
    double min_family_visibility = 0.90;   // every family
    double max_distance_median_pct = 2.0;  // pooled, % of the box diagonal
    double max_normal_median_deg = 30.0;   // pooled, against the shading normal
    // Every family must have at least this many held-out rays that reach the network: a
    // family the occupancy culls almost entirely (degenerate sampling, e.g. coordinates at
    // the edge of float range) is unmeasured, and an unmeasured asset is not shipped.
    std::uint64_t min_family_rays = 100;
    // The image rule: the combined render's FLIP over the object's own pixels in its decision
    // views (ObjectViews, ObjectFlip::combined_object) at most this.
    double max_flip = kCalibratedMaxFlip;
    Acceptance accept = Acceptance::either;
    // The image gate calibrated by what the rays already accept (docs/model.md "Judged by how
    // it looks"): the largest held-out object-pixel FLIP of the assets of real meshes that meet
    // the default ray target, rounded up (docs/image_gate.md lists them; recalibrate with
    // scripts/calibrate_image_gate when the model changes). An asset shipped by images above it
    // (a user's --gate-flip) says so (GateVerdict::above_calibrated).
    static constexpr double kCalibratedMaxFlip = 0.070;
};

// A rule a measurement misses, as numbers: what was measured, against which bound, the value
// and what the bound allows. The decisions read these; they become sentences (describe) only
// where reasons are written for people: the manifest, the text report, a candidate's stop.
enum class Measure : std::uint8_t {
    visibility,        // visibility accuracy, a fraction: pooled, or `family`'s
    family_rays,       // rays of `family` that reach the network: too few to measure
    distance,          // median distance error, % of the box diagonal
    normal,            // median shading-normal error, degrees
    image,             // FLIP of the combined render over the object's own pixels
    image_unmeasured,  // no image error: the visual check is off (value and limit unused)
};
enum class Bound : std::uint8_t {
    gate,                 // the gate, on measured metrics (gate_failures)
    target,               // the target, on measured metrics (target_misses)
    gate_out_of_reach,    // the gate, from a validation check (early_abort_reasons)
    target_out_of_reach,  // the target's visibility, from the first rung's curve (finer_grid_reason)
    larger_rung,          // what TargetStop needs, against the larger rung's curve (falls_behind)
};
struct RuleMiss {
    Measure measure = Measure::visibility;
    Bound bound = Bound::gate;
    double value = 0;                       // measured, in the measure's unit (visibility as a fraction)
    double limit = 0;                       // what the bound allows, same unit
    std::optional<samples::Family> family;  // a family's rule; none: pooled
    std::uint32_t step = 0;                 // target_out_of_reach, larger_rung: the check's step
    double larger_gain = 0;  // larger_rung: visibility (a fraction) the larger rung gained after `step`
};
// One line for people ("visibility accuracy 82.73% < gate 95%"), the text of the manifest's
// reasons after "gate: " and of the report.
std::string describe(const RuleMiss& miss);
std::vector<std::string> describe(std::span<const RuleMiss> misses);

// The gate's verdict: passed, or why not; and which rules passed (the manifest's `by`).
enum class GatePass : std::uint8_t { rays, images, both };
struct GateVerdict {
    bool passed = false;
    std::vector<std::string> reasons;  // empty when passed (written: describe()'s lines)
    std::optional<GatePass> by;        // set when passed
    // Passed by its images alone: the ray rules it fails (gate_failures), named.
    std::vector<std::string> rays_failed;
    // Passed by its images alone with an image error above Gate::kCalibratedMaxFlip: the
    // user raised the image gate (--gate-flip) and this asset needed it.
    bool above_calibrated = false;
};

// The accuracy a user asks of every shipped asset (`--target VIS,DIST,NORMAL`), on pooled
// held-out rays: visibility accuracy at least `visibility`, median distance error at most
// `distance_pct` % of the box diagonal, median shading-normal error at most `normal_deg`.
// Stricter than the gate, which is the floor below which nothing ships: an asset may pass
// the gate and miss the target, and the manifest says so; sizing makes each model as small
// as the target allows. The default is the accuracy of the default preset on CGAL's dragon and
// armadillo (docs/model.md "A 64^3 grid"): sizing keeps the full model for them, and the
// early stop (TargetStop's margins beyond it) rarely cuts their training short.
struct Target {
    double visibility = 0.985;
    double distance_pct = 0.6;
    double normal_deg = 8.0;
    // The visual term (`--target-flip`): the combined render's FLIP over the object's own
    // pixels in its decision views at most this, when the visual check ran. The default, 1,
    // asks nothing of the images: the image error of three views of 160x120 pixels varies more
    // from one draw of views to another than between the sizes of one model
    // (docs/image_gate.md), so an image term would choose sizes by the draw of views. The
    // image gate (Gate::max_flip) judges the images.
    double flip = 1.0;
};

// "VIS,DIST,NORMAL" (VIS in percent, e.g. "97,1.0,15") into `target`. False with a
// one-line `error` for anything else: not three finite numbers, VIS outside (0, 100],
// DIST outside (0, 100], NORMAL outside (0, 180].
bool parse_target(const std::string& text, Target& target, std::string& error);

// Giving up early (docs/model.md "Deciding early"): at a validation check, once training
// has seen at least `min_samples` samples, an object is abandoned (it stays BVH) when even
// the largest improvement measured from such a point to the end of training could not
// bring its validation curve to the gate. Each headroom is the largest such change measured
// on CGAL's dragon and armadillo and the hard-geometry suite, with margin
// (docs/investigations/sizing.md "Deciding early: the hard cases"); recalibrate them there
// when the model or the budget changes.
struct EarlyAbort {
    std::uint64_t min_samples = 1500000;  // before this the curve is too steep to judge
    double visibility_headroom = 0.05;    // fraction of visibility a curve may still gain
    double normal_headroom_deg = 20.0;    // degrees the median normal error may still fall
    double distance_factor = 0.35;        // final / checked median distance error, at least
};

// Stopping when the target is met (docs/model.md "Deciding early"): training ends at a
// validation check when this check and the `consecutive - 1` checks before it all meet the
// target with margins for the noise of the validation set (2^13 rays: a few tenths of a point
// of visibility), so that the held-out measure of the shipped model meets it too.
// Training an object further than its target only spends time: a user who wants more asks
// for more with --target.
struct TargetStop {
    std::uint32_t consecutive = 2;     // checks in a row: one good check may be noise; 0: never stop
    double visibility_margin = 0.003;  // validation visibility >= target + margin
    double distance_factor = 0.9;      // validation median distance <= factor x target
    double normal_margin_deg = 1.0;    // validation median normal <= target - margin
};

// Sizing to the target (docs/model.md "Sizing to the target"): the ladder is the table sizes
// from 2^ClassifyRule::min_log2_table_size up to the largest that passes the memory rule (the
// size triage gave the mesh). The search starts at 2^first_log2_table_size rows (or triage's
// size when that is smaller) and moves one rung at a time:
//   - down, when the rung met the target: the next smaller rung is trained from the steps
//     left of the preset's budget (given up early by falls_behind), and so on while each
//     smaller rung meets the target;
//   - up, when the rung ended short of the target by no more than the climb margins: the
//     next larger rung (up to triage's) is trained with a whole budget of its own.
// The smallest asset that meets the target ships. Going down never trains more steps than one
// budget; only a near miss costs a second one.
struct Sizing {
    bool explore_smaller = true;  // false: train triage's size only (--fixed-model)
    // Also measure every rung with its hash-grid features quantized to 8 bits (FORMAT.md
    // §6.4.1): the grid's bytes halve, and the option ships when it still meets the target.
    bool quantize = true;
    // A smaller rung is given up at a validation check when its visibility, plus the most
    // the larger rung's curve gained after the same step, plus this slack, stays below the
    // visibility that TargetStop asks for: it would not catch up within its budget. A smaller
    // rung runs a shorter schedule and gains more late than the larger rung did after the same
    // step; the slack covers that difference twice (docs/investigations/sizing.md "What the
    // table sizes bought, before the ladder").
    double curve_slack = 0.01;
    // The grid rung (docs/model.md "Thin geometry: a finer grid where the target needs it"):
    // when the first size's validation curve shows, once EarlyAbort may judge, that even the
    // largest improvement measured from there (finer_grid_headroom) leaves it short of the
    // target's visibility, training starts again at twice the occupancy grid's resolution,
    // up to this (0: never). Thin structure (hair, grilles) is what a coarse grid cannot
    // separate; a finer grid lowers its image error where more entry points or a wider
    // network do not (docs/investigations/judged-by-how-it-looks.md).
    std::uint32_t max_grid_resolution = 128;
    // The most visibility (a fraction) a curve may still gain from the default preset's first
    // check that may judge to the end of training: the largest gain measured on solid scans,
    // real assemblies and thin geometry, with margin (docs/investigations/judged-by-how-it-looks.md
    // "How much headroom the validation curve has").
    double finer_grid_headroom = 0.035;
    // The rung the search starts at (--first-log2-table; 0: triage's size): the size most
    // objects of the sizing set end at when each size is trained alone with the whole budget
    // (docs/investigations/sizing.md), so that most objects train once; starting at the
    // smallest would train most objects twice.
    std::uint32_t first_log2_table_size = 16;
    // How far short of the target a rung's decision-ray metrics may end for the next larger
    // rung to be tried: a near miss that one more rung closes (CGAL's armadillo, between 2^16
    // and 2^17 rows: docs/investigations/sizing.md); objects that miss by points (thin
    // geometry) do not reach it with one more rung either, and stay what the gate says.
    double climb_visibility = 0.005;     // points of visibility, as a fraction
    double climb_normal_deg = 2.0;       // degrees above the target's median normal error
    double climb_distance_factor = 1.5;  // median distance error up to this times the target's
    // Going down: a smaller rung is tried when the steps left are at least this fraction of
    // the steps the rung above used. Its schedule is compressed into the steps left, and it is
    // given up at the first check where its curve falls behind (curve_slack): a smaller table
    // can meet the target in fewer steps than the larger one needed (the blob's:
    // docs/investigations/sizing.md), but not in a small remainder of the budget.
    double descend_budget_fraction = 0.5;
};

// The gate's ray rules on measured metrics: one miss per failed rule, Bound::gate; empty when
// they pass.
std::vector<RuleMiss> gate_failures(const samples::Metrics& metrics, const Gate& gate);
// The gate's verdict on an option: `metrics` (decision rays), `flip` (the combined render's
// FLIP; none when the visual check is off) and what training says against it (divergence,
// giving up: these always fail). Gate::accept says which of the ray and image rules may pass it.
GateVerdict gate_verdict(const samples::Metrics& metrics, std::optional<double> flip,
                         std::vector<std::string> training_failures, const Gate& gate);
// What an option misses of `target`: one miss per rule, Bound::target, empty when the target
// is met. The ray rules on pooled metrics (left out when only images are accepted), the
// visual term on `flip` when there is one.
std::vector<RuleMiss> target_misses(const samples::FamilyMetrics& pooled, std::optional<double> flip,
                                    const Target& target, Acceptance accept = Acceptance::either);

// One check of the validation curve (docs/model.md "Validation curve and deciding early"):
// pooled metrics of the validation rays after `step` steps. The manifest's candidates carry
// the curve as [{"step", "visibility", "distance_pct", "normal_deg"}] (validation_json).
struct ValidationPoint {
    std::uint32_t step = 0;
    double visibility = 0;    // fraction of rays whose hit or miss is right
    double distance_pct = 0;  // median distance error, % of the box diagonal
    double normal_deg = 0;    // median normal error, degrees
};
nlohmann::json validation_json(std::span<const ValidationPoint> curve);

// Why a validation point, after `samples` training samples, shows that training cannot
// reach `gate` (Bound::gate_out_of_reach); empty when it may (or when fewer than
// rule.min_samples samples were seen).
std::vector<RuleMiss> early_abort_reasons(const ValidationPoint& point, std::uint64_t samples,
                                          const Gate& gate, const EarlyAbort& rule);

// Why the first size's curve at `point`, after `samples` training samples, asks for a finer
// grid (Sizing::max_grid_resolution; Bound::target_out_of_reach); none when it does not (or
// too early to judge).
std::optional<RuleMiss> finer_grid_reason(const ValidationPoint& point, std::uint64_t samples,
                                          const Target& aim, const EarlyAbort& abort, const Sizing& rule);

// The target training aims at: `target`, made at least as strict as `gate` on each pooled
// rule, since a model that meets a lenient target below the gate still may not ship.
Target effective_target(const Target& target, const Gate& gate);

// Whether a validation point meets `target` with the margins of `rule`.
bool meets_target_with_margin(const ValidationPoint& point, const Target& target, const TargetStop& rule);

// Whether a rung whose decision-ray metrics are `pooled` missed `target` by no more than the
// climb margins of `rule`, so that the next larger rung may meet it.
bool near_target(const samples::FamilyMetrics& pooled, const Target& target, const Sizing& rule);

// Why a smaller rung, at a validation point, cannot catch up with the target given the larger
// rung's validation curve `larger` (Bound::larger_rung); none when it may. Only steps within
// the larger curve are judged.
std::optional<RuleMiss> falls_behind(const ValidationPoint& point, std::span<const ValidationPoint> larger,
                                     const Target& target, const TargetStop& stop, const Sizing& rule);

}  // namespace lsnif::converter
