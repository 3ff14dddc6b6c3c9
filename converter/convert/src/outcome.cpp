// The one JSON codec of a mesh's outcome (lsnif/converter/outcome.hpp): the manifest's mesh
// entry, the run's report and the cache record, written and read back strictly.
#include <lsnif/converter/json_reader.hpp>
#include <lsnif/converter/metadata_names.hpp>
#include <lsnif/converter/outcome.hpp>

#include <cstring>

namespace lsnif::converter {

using json_reader::Reader;
using nlohmann::json;

namespace {

constexpr std::string_view kClassNames[] = {"simple", "complex", "failed", "deferred"};
constexpr std::string_view kDecisionNames[kDecisionCount] = {
    "forced_simple",       "few_triangles", "not_modelable",     "voxelization_failed", "no_memory_benefit",
    "decided_early",       "below_gate",    "asset_not_smaller", "budget_met",          "other_shard",
    "left_to_another_job", "planned",       "shipped",           "encode_failed",       "write_failed"};
constexpr std::string_view kStageNames[kStageCount] = {
    "classify", "voxelize", "sample", "prepare", "train", "validate", "prune", "evaluate", "visual", "write"};
constexpr const char* kTargetMetText = "the validation curve met the target";
constexpr const char* kGivenUpPrefix = "given up: ";
constexpr const char* kStoppedEarlyReason = "validation curve met the target";

// The index of `name` in `names`, or nothing.
template <std::size_t N>
std::optional<std::size_t> name_index(const std::string_view (&names)[N], const std::string& name) {
    for (std::size_t i = 0; i < N; ++i)
        if (names[i] == name) return i;
    return std::nullopt;
}

json vec3(const std::array<float, 3>& v) {
    return json::array({v[0], v[1], v[2]});
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

void read_family(Reader& r, samples::FamilyMetrics& f) {
    r.read("rays", f.rays);
    r.read("visibility_accuracy", f.visibility_accuracy);
    r.read("false_hit_rate", f.false_hit_rate);
    r.read("false_miss_rate", f.false_miss_rate);
    r.read("distance_error_median_pct", f.distance_median_pct);
    r.read("distance_error_p95_pct", f.distance_p95_pct);
    r.read("normal_error_median_deg", f.normal_median_deg);
    r.read("normal_error_p95_deg", f.normal_p95_deg);
    r.read("geometric_normal_error_median_deg", f.geometric_normal_median_deg);
    r.read("culled_fraction", f.culled_fraction);
}

void read_flip(Reader& r, render::ObjectFlip& f);

void read_held_out(Reader& r, HeldOut& h) {
    if (r.has("flip")) r.nested("flip", [&](Reader& f) { read_flip(f, h.flip.emplace()); });
    if (r.has("escape_points")) r.read("escape_points", h.escape_points);
    r.read("held_out_rays", h.rays);
    r.nested("families", [&](Reader& fr) {
        for (int f = 0; f < samples::kFamilyCount; ++f)
            fr.nested(samples::family_name(samples::Family(f)),
                      [&](Reader& x) { read_family(x, h.metrics.family[f]); });
        fr.nested("pooled", [&](Reader& x) { read_family(x, h.metrics.pooled); });
    });
    r.nested("gate", [&](Reader& g) {
        g.read("passed", h.gate.passed);
        if (g.has("reasons")) g.read("reasons", h.gate.reasons);
        if (g.has("by")) {
            std::string by;
            g.read("by", by);
            if (by == "rays")
                h.gate.by = GatePass::rays;
            else if (by == "images")
                h.gate.by = GatePass::images;
            else if (by == "both")
                h.gate.by = GatePass::both;
            else if (g.ok())
                g.fail("by", "not rays, images or both: " + by);
        }
        if (g.has("rays_failed")) g.read("rays_failed", h.gate.rays_failed);
        std::optional<bool> above;
        g.read("above_calibrated_gate", above);
        h.gate.above_calibrated = above.value_or(false);
        if (g.ok() && h.gate.passed != h.gate.reasons.empty())
            g.fail("reasons",
                   h.gate.passed ? "present although the gate passed" : "missing although the gate failed");
        if (g.ok() && h.gate.passed != h.gate.by.has_value())
            g.fail("by",
                   h.gate.passed ? "missing although the gate passed" : "present although the gate failed");
    });
}

}  // namespace

json object_flip_json(const render::ObjectFlip& f) {
    return {{"combined", f.combined},
            {"combined_object", f.combined_object},
            {"combined_object_p95", f.combined_object_p95}};
}

namespace {

void read_flip(Reader& r, render::ObjectFlip& f) {
    r.read("combined", f.combined);
    r.read("combined_object", f.combined_object);
    r.read("combined_object_p95", f.combined_object_p95);
}

json stats_json(const MeshStats& s) {
    json j = {{"box_min", vec3(s.box_min)},
              {"box_max", vec3(s.box_max)},
              {"area_ratio", s.area_ratio},
              {"components", s.components},
              {"closed", s.closed},
              {"solid", s.solid},
              {"log2_table_size", s.log2_table_size},
              {"bvh", {{"embree", s.bvh.embree}, {"compressed", s.bvh.compressed}}},
              {"resident_estimate", s.resident_estimate}};
    if (s.occupied_fraction) j["occupied_fraction"] = *s.occupied_fraction;
    if (s.mean_occupied_per_ray) j["mean_occupied_per_ray"] = *s.mean_occupied_per_ray;
    if (s.training_rays) j["training_rays"] = *s.training_rays;
    return j;
}

void read_stats(Reader& r, MeshStats& s) {
    r.read("box_min", s.box_min);
    r.read("box_max", s.box_max);
    r.read("area_ratio", s.area_ratio);
    r.read("components", s.components);
    r.read("closed", s.closed);
    r.read("solid", s.solid);
    r.read("log2_table_size", s.log2_table_size);
    r.nested("bvh", [&](Reader& b) {
        b.read("embree", s.bvh.embree);
        b.read("compressed", s.bvh.compressed);
    });
    r.read("resident_estimate", s.resident_estimate);
    r.read("occupied_fraction", s.occupied_fraction);
    r.read("mean_occupied_per_ray", s.mean_occupied_per_ray);
    r.read("training_rays", s.training_rays);
}

void read_curve(Reader& r, const char* key, std::vector<ValidationPoint>& curve) {
    r.records(key, curve, [](Reader& p, ValidationPoint& v) {
        p.read("step", v.step);
        p.read("visibility", v.visibility);
        p.read("distance_pct", v.distance_pct);
        p.read("normal_deg", v.normal_deg);
    });
}

json candidate_json(const CandidateRecord& c, OutcomeFields fields) {
    json j = {
        {"log2_table_size", c.log2_table_size},
        {"grid_resolution", c.grid_resolution},
        {"hidden_width", c.hidden_width},
        {"grid", grid_encoding_name(std::uint32_t(c.grid))},
        {"bytes", c.bytes},
        {"resident_bytes", c.resident_bytes},
        {"steps", c.steps},
        {"steps_planned", c.steps_planned},
        {"held_out",
         {{"visibility", c.visibility}, {"distance_pct", c.distance_pct}, {"normal_deg", c.normal_deg}}},
        {"decided",
         {{"visibility", c.decided_visibility},
          {"distance_pct", c.decided_distance_pct},
          {"normal_deg", c.decided_normal_deg}}},
        {"gate_passed", c.gate_passed},
        {"target_met", c.target_met},
        {"memory_rule_passed", c.memory_rule_passed},
        {"outcome", candidate_outcome_text(c.outcome, c.of)}};
    if (c.seconds && fields == OutcomeFields::all) j["seconds"] = *c.seconds;
    if (c.validation) j["validation"] = validation_json(*c.validation);
    if (c.stop == StopKind::target_met) j["stopped"] = kTargetMetText;
    if (c.stop == StopKind::given_up) j["stopped"] = kGivenUpPrefix + c.stop_why;
    if (!c.pruned_neurons.empty()) j["pruned_neurons"] = c.pruned_neurons;
    if (c.flip) j["flip"] = object_flip_json(*c.flip);
    return j;
}

void read_candidate(Reader& r, CandidateRecord& c, std::size_t of) {
    r.read("log2_table_size", c.log2_table_size);
    r.read("grid_resolution", c.grid_resolution);
    r.read("hidden_width", c.hidden_width);
    std::string grid;
    r.read("grid", grid);
    if (r.ok() && grid == grid_encoding_name(std::uint32_t(format::GridEncoding::fp16)))
        c.grid = format::GridEncoding::fp16;
    else if (r.ok() && grid == grid_encoding_name(std::uint32_t(format::GridEncoding::u8_affine)))
        c.grid = format::GridEncoding::u8_affine;
    else if (r.ok())
        r.fail("grid", "not a grid encoding: " + grid);
    r.read("bytes", c.bytes);
    r.read("resident_bytes", c.resident_bytes);
    r.read("steps", c.steps);
    r.read("steps_planned", c.steps_planned);
    r.read("seconds", c.seconds);
    r.nested("held_out", [&](Reader& h) {
        h.read("visibility", c.visibility);
        h.read("distance_pct", c.distance_pct);
        h.read("normal_deg", c.normal_deg);
    });
    r.nested("decided", [&](Reader& h) {
        h.read("visibility", c.decided_visibility);
        h.read("distance_pct", c.decided_distance_pct);
        h.read("normal_deg", c.decided_normal_deg);
    });
    r.read("gate_passed", c.gate_passed);
    r.read("target_met", c.target_met);
    r.read("memory_rule_passed", c.memory_rule_passed);
    c.of = of;
    std::string outcome;
    r.read("outcome", outcome);
    bool known = false;
    for (auto o : {CandidateOutcome::chosen_meets_target, CandidateOutcome::chosen_passes_gate,
                   CandidateOutcome::fails_gate, CandidateOutcome::fails_memory_rule,
                   CandidateOutcome::smaller_meets_target, CandidateOutcome::misses_target})
        if (r.ok() && outcome == candidate_outcome_text(o, of)) c.outcome = o, known = true;
    if (r.ok() && !known) r.fail("outcome", "not an outcome: " + outcome);
    if (r.has("validation")) read_curve(r, "validation", c.validation.emplace());
    std::string stopped;
    if (r.has("stopped")) {
        r.read("stopped", stopped);
        if (stopped == kTargetMetText) {
            c.stop = StopKind::target_met;
        } else if (stopped.rfind(kGivenUpPrefix, 0) == 0) {
            c.stop = StopKind::given_up;
            c.stop_why = stopped.substr(std::strlen(kGivenUpPrefix));
        } else if (r.ok()) {
            r.fail("stopped", "not a reason to stop: " + stopped);
        }
    }
    if (r.has("pruned_neurons")) r.read("pruned_neurons", c.pruned_neurons);
    if (r.has("flip")) r.nested("flip", [&](Reader& f) { read_flip(f, c.flip.emplace()); });
}

json target_json(const TargetVerdict& t) {
    json j = {{"visibility", t.target.visibility},
              {"distance_pct", t.target.distance_pct},
              {"normal_deg", t.target.normal_deg},
              {"flip", t.target.flip},
              {"met", t.misses.empty()}};
    if (!t.misses.empty()) j["misses"] = t.misses;
    return j;
}

void read_target(Reader& r, TargetVerdict& t) {
    r.read("visibility", t.target.visibility);
    r.read("distance_pct", t.target.distance_pct);
    r.read("normal_deg", t.target.normal_deg);
    r.read("flip", t.target.flip);
    bool met = false;
    r.read("met", met);
    if (r.has("misses")) r.read("misses", t.misses);
    if (r.ok() && met != t.misses.empty())
        r.fail("misses", met ? "present although met" : "missing although not met");
}

// Where the mesh is in its scene: left out of a cache record, which any scene may restore.
void write_placement(const MeshOutcome& o, json& j) {
    j["id"] = o.id;
    j["name"] = o.name;
    j["input"] = o.input;
    j["source_mesh"] = o.source_mesh;
    j["instances"] = o.instances;
}

void read_placement(Reader& r, MeshOutcome& o) {
    r.read("id", o.id);
    r.read("name", o.name);
    r.read("input", o.input);
    r.read("source_mesh", o.source_mesh);
    r.read("instances", o.instances);
}

void write_results(const MeshOutcome& o, OutcomeFields fields, json& j) {
    if (o.held_out) j["metrics"] = held_out_json(*o.held_out);
    if (!o.candidates.empty()) {
        j["candidates"] = json::array();
        for (const CandidateRecord& c : o.candidates) j["candidates"].push_back(candidate_json(c, fields));
    }
    if (o.validation) j["validation"] = validation_json(*o.validation);
    if (o.stopped_early)
        j["stopped_early"] = {{"step", o.stopped_early->step},
                              {"steps", o.stopped_early->steps},
                              {"reason", kStoppedEarlyReason}};
    if (o.target) j["target"] = target_json(*o.target);
    if (o.held_out_images) j["held_out_images"] = object_flip_json(*o.held_out_images);
    if (o.asset) {
        j["lsnif"] = {
            {"file", o.asset->file}, {"bytes", o.asset->bytes}, {"resident_bytes", o.asset->resident_bytes}};
        if (o.asset->reused && fields == OutcomeFields::all) j["lsnif"]["reused"] = *o.asset->reused;
    }
}

void read_results(Reader& r, MeshOutcome& o) {
    if (r.has("metrics")) r.nested("metrics", [&](Reader& m) { read_held_out(m, o.held_out.emplace()); });
    if (r.has("candidates")) {
        const std::size_t of = r.at("candidates").is_array() ? r.at("candidates").size() : 0;
        r.records("candidates", o.candidates,
                  [of](Reader& c, CandidateRecord& rec) { read_candidate(c, rec, of); });
    }
    if (r.has("validation")) read_curve(r, "validation", o.validation.emplace());
    if (r.has("stopped_early"))
        r.nested("stopped_early", [&](Reader& s) {
            StoppedEarly& e = o.stopped_early.emplace();
            s.read("step", e.step);
            s.read("steps", e.steps);
            std::string reason;
            s.read("reason", reason);
            if (s.ok() && reason != kStoppedEarlyReason) s.fail("reason", "not a reason to stop: " + reason);
        });
    if (r.has("target")) r.nested("target", [&](Reader& t) { read_target(t, o.target.emplace()); });
    if (r.has("held_out_images"))
        r.nested("held_out_images", [&](Reader& f) { read_flip(f, o.held_out_images.emplace()); });
    if (r.has("lsnif"))
        r.nested("lsnif", [&](Reader& a) {
            AssetFile& f = o.asset.emplace();
            a.read("file", f.file);
            a.read("bytes", f.bytes);
            a.read("resident_bytes", f.resident_bytes);
            a.read("reused", f.reused);
        });
}

// What a record must hold beyond its fields' types: an asset exactly when the decision ships one.
std::string consistency_problem(const MeshOutcome& o) {
    const bool ships = o.decision == Decision::shipped;
    if (ships != o.asset.has_value())
        return ships ? "lsnif: missing for a shipped mesh" : "lsnif: present for a mesh that was not shipped";
    if (o.asset && (o.asset->file.empty() || o.asset->file.find('/') != std::string::npos ||
                    o.asset->file.find("..") != std::string::npos))
        return "lsnif.file: not a file name in the output directory";
    return {};
}

}  // namespace

MeshClass mesh_class(Decision d) {
    switch (d) {
        case Decision::planned:
        case Decision::shipped: return MeshClass::complex;
        case Decision::encode_failed:
        case Decision::write_failed: return MeshClass::failed;
        case Decision::left_to_another_job: return MeshClass::deferred;
        default: return MeshClass::simple;
    }
}

bool decided_in_triage(Decision d) {
    return d == Decision::forced_simple || d == Decision::few_triangles || d == Decision::not_modelable ||
           d == Decision::voxelization_failed || d == Decision::no_memory_benefit;
}

std::string_view class_name(MeshClass c) {
    return kClassNames[std::size_t(c)];
}

std::string_view decision_name(Decision d) {
    return kDecisionNames[std::size_t(d)];
}

std::string_view stage_name(Stage s) {
    return kStageNames[std::size_t(s)];
}

bool Timings::empty() const {
    for (const auto& s : seconds)
        if (s) return false;
    return true;
}

double Timings::total() const {
    double t = 0;
    for (const auto& s : seconds) t += s.value_or(0);
    return t;
}

MeshOutcome& MeshOutcome::settle(Decision d, std::string why) {
    decision = d;
    if (!why.empty()) reasons.push_back(std::move(why));
    return *this;
}

std::string choice_text(CandidateOutcome o, std::size_t of) {
    if (o == CandidateOutcome::chosen_meets_target)
        return "the smallest of " + std::to_string(of) + " candidates that meets the target";
    if (o == CandidateOutcome::chosen_passes_gate)
        return "no candidate meets the target; the largest passes the gate";
    return {};
}

std::string candidate_outcome_text(CandidateOutcome o, std::size_t of) {
    switch (o) {
        case CandidateOutcome::chosen_meets_target:
        case CandidateOutcome::chosen_passes_gate: return "chosen: " + choice_text(o, of);
        case CandidateOutcome::fails_gate: return "fails the gate";
        case CandidateOutcome::fails_memory_rule: return "fails the memory rule";
        case CandidateOutcome::smaller_meets_target:
            return "meets the target, but a smaller candidate does too";
        case CandidateOutcome::misses_target: return "misses the target";
    }
    return {};
}

json held_out_json(const HeldOut& h) {
    json families;
    for (int f = 0; f < samples::kFamilyCount; ++f)
        families[samples::family_name(samples::Family(f))] = family_json(h.metrics.family[f]);
    families["pooled"] = family_json(h.metrics.pooled);
    json gate = {{"passed", h.gate.passed}};
    if (!h.gate.reasons.empty()) gate["reasons"] = h.gate.reasons;
    if (h.gate.by)
        gate["by"] = *h.gate.by == GatePass::rays     ? "rays"
                     : *h.gate.by == GatePass::images ? "images"
                                                      : "both";
    if (!h.gate.rays_failed.empty()) gate["rays_failed"] = h.gate.rays_failed;
    if (h.gate.above_calibrated) gate["above_calibrated_gate"] = true;
    json j = {{"held_out_rays", h.rays},
              {"families", families},
              {"gate", gate},
              {"escape_points", h.escape_points}};
    if (h.flip) j["flip"] = object_flip_json(*h.flip);
    return j;
}

base::Result<HeldOut, std::string> held_out_from_json(const json& j) {
    HeldOut h;
    Reader r(j, "");
    read_held_out(r, h);
    if (!r.ok()) return r.error();
    return h;
}

json outcome_json(const MeshOutcome& o, OutcomeFields fields) {
    json j = json::object();
    if (fields != OutcomeFields::result) write_placement(o, j);
    j["triangles"] = o.triangles;
    j["vertices"] = o.vertices;
    j["geometry_hash"] = o.geometry_hash;
    j["class"] = class_name(o.cls());
    j["decision"] = decision_name(o.decision);
    j["reasons"] = o.reasons;
    if (o.stats) j["stats"] = stats_json(*o.stats);
    if (fields == OutcomeFields::all) {
        json t = json::object();
        for (std::size_t s = 0; s < kStageCount; ++s)
            if (o.timings.seconds[s]) t[std::string(kStageNames[s])] = *o.timings.seconds[s];
        j["timings"] = t;
    }
    write_results(o, fields, j);
    if (o.memory) {
        j["memory"] = {{"before", o.memory->before}, {"after", o.memory->after}};
        if (o.memory->estimated) j["memory"]["estimated"] = true;
    }
    if (o.shard) j["shard"] = *o.shard;
    if (o.cache_key) j["cache_key"] = *o.cache_key;
    if (o.estimated_ms) j["estimated_ms"] = *o.estimated_ms;
    return j;
}

base::Result<MeshOutcome, std::string> outcome_from_json(const json& j, OutcomeFields fields) {
    MeshOutcome o;
    Reader r(j, "");
    if (fields != OutcomeFields::result) read_placement(r, o);
    r.read("triangles", o.triangles);
    r.read("vertices", o.vertices);
    r.read("geometry_hash", o.geometry_hash);
    std::string cls, decision;
    r.read("class", cls);
    r.read("decision", decision);
    if (r.ok()) {
        if (auto d = name_index(kDecisionNames, decision))
            o.decision = Decision(*d);
        else
            r.fail("decision", "not a decision: " + decision);
    }
    if (r.ok() && cls != class_name(o.cls())) r.fail("class", cls + " does not go with decision " + decision);
    r.read("reasons", o.reasons);
    if (r.has("stats")) r.nested("stats", [&](Reader& s) { read_stats(s, o.stats.emplace()); });
    if (r.has("timings"))
        r.nested("timings", [&](Reader& t) {
            for (std::size_t s = 0; s < kStageCount; ++s)
                t.read(std::string(kStageNames[s]).c_str(), o.timings.seconds[s]);
        });
    read_results(r, o);
    if (r.has("memory"))
        r.nested("memory", [&](Reader& m) {
            MeshMemory& mem = o.memory.emplace();
            m.read("before", mem.before);
            m.read("after", mem.after);
            std::optional<bool> estimated;
            m.read("estimated", estimated);
            mem.estimated = estimated.value_or(false);
        });
    r.read("shard", o.shard);
    r.read("cache_key", o.cache_key);
    r.read("estimated_ms", o.estimated_ms);
    if (!r.ok()) return r.error();
    if (std::string why = consistency_problem(o); !why.empty()) return why;
    return o;
}

json input_json(const InputRecord& in) {
    json j = {{"path", in.path}, {"given", in.given}, {"status", in.ok() ? "ok" : "error"}};
    if (in.error) j["error"] = *in.error;
    if (!in.warnings.empty()) j["warnings"] = in.warnings;
    return j;
}

base::Result<InputRecord, std::string> input_from_json(const json& j) {
    InputRecord in;
    Reader r(j, "");
    r.read("path", in.path);
    r.read("given", in.given);
    std::string status;
    r.read("status", status);
    r.read("error", in.error);
    if (r.has("warnings")) r.read("warnings", in.warnings);
    if (r.ok() && status != (in.ok() ? "ok" : "error"))
        r.fail("status", status + " does not go with " + (in.ok() ? "no error" : "an error"));
    if (!r.ok()) return r.error();
    return in;
}

SceneMemory scene_memory(const std::vector<MeshOutcome>& meshes, BvhYardstick yardstick, std::uint64_t budget,
                         bool estimated) {
    SceneMemory m;
    m.yardstick = yardstick;
    for (const MeshOutcome& o : meshes) {
        m.before += o.memory->before;
        m.after += o.memory->after;
    }
    if (budget > 0) m.budget = budget;
    m.estimated = estimated;
    return m;
}

base::Result<SceneMemory, std::string> scene_memory_from_json(const json& j) {
    SceneMemory m;
    Reader r(j, "");
    std::string yardstick;
    r.read("yardstick", yardstick);
    if (r.ok() && !parse_bvh_yardstick(yardstick, m.yardstick))
        r.fail("yardstick", "not a BVH yardstick: " + yardstick);
    r.read("before", m.before);
    r.read("after", m.after);
    r.read("budget", m.budget);
    if (r.has("estimated")) r.read("estimated", m.estimated);
    if (r.ok() && m.budget.has_value() != r.has("fits")) r.fail("fits", "goes with budget, and only with it");
    if (!r.ok()) return r.error();
    return m;
}

json scene_memory_json(const SceneMemory& m) {
    json j = {{"yardstick", bvh_yardstick_name(m.yardstick)}, {"before", m.before}, {"after", m.after}};
    if (m.budget) {
        j["budget"] = *m.budget;
        j["fits"] = m.fits();
    }
    if (m.estimated) j["estimated"] = true;
    return j;
}

}  // namespace lsnif::converter
