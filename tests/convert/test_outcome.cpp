// The typed outcome of a mesh and its one JSON codec (lsnif/converter/outcome.hpp): what the
// manifest, the report and the cache record hold, read back strictly.
#include <lsnif/converter/outcome.hpp>

#include <doctest/doctest.h>

#include <set>

using namespace lsnif::converter;
using nlohmann::json;

namespace {

lsnif::samples::FamilyMetrics family(double v) {
    lsnif::samples::FamilyMetrics f;
    f.rays = 1000 + std::uint64_t(v * 100);
    f.visibility_accuracy = 0.9 + v / 100;
    f.false_hit_rate = 0.01 * v;
    f.false_miss_rate = 0.02 * v;
    f.distance_median_pct = 0.3 + v;
    f.distance_p95_pct = 2.5 + v;
    f.normal_median_deg = 6.75 + v;
    f.normal_p95_deg = 40.125 + v;
    f.geometric_normal_median_deg = 12.5 + v;
    f.culled_fraction = 0.0625 * v;
    return f;
}

// An outcome with every optional part present, as a shipped mesh of a dry run never is, so
// that the codec is exercised whole.
MeshOutcome full_outcome() {
    MeshOutcome o;
    o.id = 7;
    o.name = "dragon \"quoted\"";
    o.input = 2;
    o.source_mesh = 3;
    o.triangles = 20000;
    o.vertices = 10000;
    o.instances = 3;
    o.geometry_hash = "00ff";
    o.decision = Decision::shipped;
    o.reasons = {"Embree BVH 1 bytes vs LSNIF 1 bytes (1.00x)", "20000 triangles"};
    MeshStats& s = o.stats.emplace();
    s.box_min = {-1.5f, 0.1f, 1e-7f};
    s.box_max = {2.f, 3.25f, 1e6f};
    s.area_ratio = 1.0 / 3.0;
    s.components = 4;
    s.closed = true;
    s.solid = false;
    s.log2_table_size = 17;
    s.bvh = {1234567, 98000};
    s.resident_estimate = 400000;
    s.occupied_fraction = 0.1;
    s.mean_occupied_per_ray = 4.2;
    s.training_rays = 1u << 20;
    o.timings.add(Stage::classify, 0.25);
    o.timings.add(Stage::train, 10.5);
    o.timings.add(Stage::train, 1.0);
    HeldOut& h = o.held_out.emplace();
    h.rays = 65536;
    for (int f = 0; f < lsnif::samples::kFamilyCount; ++f) h.metrics.family[f] = family(f + 1);
    h.metrics.pooled = family(0.5);
    h.gate.passed = true;
    h.gate.by = GatePass::images;
    h.gate.rays_failed = {"pooled visibility 94.00 % < 95.00 %"};
    h.gate.above_calibrated = true;
    h.flip = lsnif::render::ObjectFlip{0.034, 0.12, 0.0075};
    h.escape_points = 2;
    CandidateRecord c;
    c.log2_table_size = 17;
    c.grid_resolution = 64;
    c.hidden_width = {120, 97};
    c.grid = lsnif::format::GridEncoding::fp16;
    c.bytes = 900000;
    c.resident_bytes = 1500000;
    c.steps = 960;
    c.steps_planned = 1200;
    c.seconds = 12.5;
    c.visibility = 0.987;
    c.distance_pct = 0.31;
    c.normal_deg = 6.9;
    c.decided_visibility = 0.986;
    c.decided_distance_pct = 0.32;
    c.decided_normal_deg = 7.0;
    c.flip = lsnif::render::ObjectFlip{0.034, 0.12, 0.0075};
    c.gate_passed = c.target_met = c.memory_rule_passed = true;
    c.outcome = CandidateOutcome::smaller_meets_target;
    c.of = 2;
    c.validation = std::vector<ValidationPoint>{{120, 0.9, 1.5, 20.0}, {240, 0.95, 0.75, 10.0}};
    c.stop = StopKind::target_met;
    c.pruned_neurons = {8, 31};
    o.candidates.push_back(c);
    c.grid = lsnif::format::GridEncoding::u8_affine;
    c.bytes = 450000;
    c.resident_bytes = 890001;
    c.outcome = CandidateOutcome::chosen_meets_target;
    c.validation.reset();
    c.stop = StopKind::given_up;
    c.stop_why = "validation visibility 80.0 % cannot reach the gate's 95.0 %";
    c.pruned_neurons.clear();
    o.candidates.push_back(c);
    o.validation = std::vector<ValidationPoint>{{120, 0.9, 1.5, 20.0}};
    o.stopped_early = StoppedEarly{960, 1200};
    o.target = TargetVerdict{Target{}, {"visibility 98.00 % < target 98.50 %"}};
    o.held_out_images = lsnif::render::ObjectFlip{0.041, 0.15, 0.009};
    o.asset = AssetFile{"0123456789abcdef.lsnif", 450123, 890001, true};
    o.memory = MeshMemory{1234567, 450123, false};
    o.shard = 2;
    o.cache_key = "abc";
    o.estimated_ms = 17000;
    return o;
}

}  // namespace

TEST_CASE("every decision implies one class, and every name reads back as itself") {
    std::set<std::string_view> names;
    for (std::size_t d = 0; d < kDecisionCount; ++d) {
        MeshOutcome o;
        o.decision = Decision(d);
        if (o.decision == Decision::shipped) o.asset = AssetFile{"a.lsnif", 1, 2, std::nullopt};
        names.insert(decision_name(o.decision));
        const json j = outcome_json(o);
        CHECK(j["decision"] == decision_name(o.decision));
        CHECK(j["class"] == class_name(o.cls()));
        auto back = outcome_from_json(j);
        REQUIRE_MESSAGE(back.ok(), back.error());
        CHECK(back->decision == o.decision);
    }
    CHECK(names.size() == kDecisionCount);
    CHECK(mesh_class(Decision::shipped) == MeshClass::complex);
    CHECK(mesh_class(Decision::planned) == MeshClass::complex);
    CHECK(mesh_class(Decision::write_failed) == MeshClass::failed);
    CHECK(mesh_class(Decision::encode_failed) == MeshClass::failed);
    CHECK(mesh_class(Decision::left_to_another_job) == MeshClass::deferred);
    CHECK(mesh_class(Decision::below_gate) == MeshClass::simple);
}

TEST_CASE("an outcome survives its JSON exactly, in each kind of record") {
    const MeshOutcome o = full_outcome();
    const json all = outcome_json(o);
    auto back = outcome_from_json(all);
    REQUIRE_MESSAGE(back.ok(), back.error());
    CHECK(outcome_json(*back) == all);
    CHECK(back->stats->box_min == o.stats->box_min);  // floats through doubles, bit for bit
    CHECK(back->held_out->metrics.family[2].normal_p95_deg == o.held_out->metrics.family[2].normal_p95_deg);
    CHECK(back->candidates[1].stop_why == o.candidates[1].stop_why);
    CHECK(back->timings.seconds[std::size_t(Stage::train)] == 11.5);
    CHECK(all["candidates"][1]["outcome"] == "chosen: the smallest of 2 candidates that meets the target");

    // Reproducible: what differs between runs of one conversion is left out.
    const json rep = outcome_json(o, OutcomeFields::reproducible);
    CHECK_FALSE(rep.contains("timings"));
    CHECK_FALSE(rep["lsnif"].contains("reused"));
    CHECK_FALSE(rep["candidates"][0].contains("seconds"));
    CHECK(rep["id"] == 7);
    auto rep_back = outcome_from_json(rep, OutcomeFields::reproducible);
    REQUIRE_MESSAGE(rep_back.ok(), rep_back.error());
    CHECK(outcome_json(*rep_back, OutcomeFields::reproducible) == rep);

    // A cache record: reproducible, and nothing of where the mesh is in a scene.
    const json result = outcome_json(o, OutcomeFields::result);
    for (const char* k : {"id", "name", "input", "source_mesh", "instances", "timings"})
        CHECK_FALSE(result.contains(k));
    auto result_back = outcome_from_json(result, OutcomeFields::result);
    REQUIRE_MESSAGE(result_back.ok(), result_back.error());
    CHECK(outcome_json(*result_back, OutcomeFields::result) == result);
    CHECK_FALSE(outcome_from_json(result).ok());  // a manifest entry needs its placement
}

TEST_CASE("outcome_from_json refuses what it did not write and names the field") {
    const json good = outcome_json(full_outcome());
    auto error_of = [](const json& j) {
        auto r = outcome_from_json(j);
        return r.ok() ? std::string("accepted") : r.error();
    };
    auto without = [&](std::initializer_list<const char*> path) {
        json j = good;
        json* at = &j;
        auto it = path.begin();
        for (; std::next(it) != path.end(); ++it) at = &(*at)[*it];
        at->erase(*it);
        return error_of(j);
    };
    auto with = [&](std::initializer_list<const char*> path, json value) {
        json j = good;
        json* at = &j;
        for (const char* k : path) at = &(*at)[k];
        *at = std::move(value);
        return error_of(j);
    };
    CHECK(without({"decision"}) == "decision: missing");
    CHECK(without({"stats", "bvh", "compressed"}) == "stats.bvh.compressed: missing");
    CHECK(without({"lsnif", "resident_bytes"}) == "lsnif.resident_bytes: missing");
    CHECK(without({"metrics", "families", "surface", "normal_error_median_deg"}) ==
          "metrics.families.surface.normal_error_median_deg: missing");
    CHECK(with({"stats", "components"}, -1) == "stats.components: not a whole number in range");
    CHECK(with({"stats", "log2_table_size"}, 1ull << 40) ==
          "stats.log2_table_size: not a whole number in range");
    CHECK(with({"triangles"}, "20000") == "triangles: not a whole number in range");
    CHECK(with({"metrics", "families", "pooled", "visibility_accuracy"}, nullptr) ==
          "metrics.families.pooled.visibility_accuracy: not a number");
    CHECK(with({"decision"}, "shiped") == "decision: not a decision: shiped");
    CHECK(with({"class"}, "simple") == "class: simple does not go with decision shipped");
    CHECK(with({"stats", "box_min"}, json::array({1, 2})) == "stats.box_min: not 3 numbers");
    CHECK(with({"metrics", "gate", "passed"}, false) ==
          "metrics.gate.reasons: missing although the gate failed");
    CHECK(with({"metrics", "gate", "by"}, "luck") == "metrics.gate.by: not rays, images or both: luck");
    CHECK(without({"metrics", "flip", "combined"}) == "metrics.flip.combined: missing");
    CHECK(without({"held_out_images", "combined_object_p95"}) ==
          "held_out_images.combined_object_p95: missing");
    CHECK(with({"target", "met"}, true) == "target.misses: present although met");
    CHECK(with({"lsnif", "file"}, "../x.lsnif") == "lsnif.file: not a file name in the output directory");
    json not_shipped = good;
    not_shipped["decision"] = "below_gate";
    not_shipped["class"] = "simple";
    CHECK(error_of(not_shipped) == "lsnif: present for a mesh that was not shipped");
    CHECK(without({"lsnif"}) == "lsnif: missing for a shipped mesh");
    json bad_candidate = good;
    bad_candidate["candidates"][1]["outcome"] = "chosen: the best";
    CHECK(error_of(bad_candidate) == "candidates[1].outcome: not an outcome: chosen: the best");
    bad_candidate = good;
    bad_candidate["candidates"][0]["stopped"] = "tired";
    CHECK(error_of(bad_candidate) == "candidates[0].stopped: not a reason to stop: tired");
    bad_candidate = good;
    bad_candidate["candidates"][0]["grid"] = "fp8";
    CHECK(error_of(bad_candidate) == "candidates[0].grid: not a grid encoding: fp8");
    CHECK(error_of(json::array()) == "not an object");
    CHECK(with({"stats"}, 3) == "stats: not an object");
}

TEST_CASE("held-out metrics as an asset's metadata stores them read back strictly") {
    const HeldOut h = full_outcome().held_out.value();
    const json j = held_out_json(h);
    auto back = held_out_from_json(j);
    REQUIRE(back.ok());
    CHECK(held_out_json(*back) == j);
    CHECK(back->escape_points == 2);
    json older = j;
    older["families"]["pooled"].erase("geometric_normal_error_median_deg");  // a field this version writes
    CHECK_FALSE(held_out_from_json(older).ok());
    // Assets written before the escape rule have no escape_points: off.
    json before_escape = j;
    before_escape.erase("escape_points");
    auto off = held_out_from_json(before_escape);
    REQUIRE(off.ok());
    CHECK(off->escape_points == 0);
}

TEST_CASE("inputs and the scene's memory: records and sums") {
    InputRecord ok{"../scene.glb", "/abs/scene.glb", std::nullopt, {"a warning"}};
    auto back = input_from_json(input_json(ok));
    REQUIRE(back.ok());
    CHECK(input_json(*back) == input_json(ok));
    CHECK(input_json(ok)["status"] == "ok");
    InputRecord failed{"x.obj", "x.obj", std::string("x.obj: cannot open"), {}};
    CHECK(input_json(failed)["status"] == "error");
    json lying = input_json(failed);
    lying["status"] = "ok";
    CHECK_FALSE(input_from_json(lying).ok());

    std::vector<MeshOutcome> meshes(2);
    meshes[0].memory = MeshMemory{100, 10, false};
    meshes[1].memory = MeshMemory{50, 50, false};
    const SceneMemory m = scene_memory(meshes, BvhYardstick::compressed, 40, false);
    CHECK(m.before == 150);
    CHECK(m.after == 60);
    CHECK_FALSE(m.fits());
    CHECK(scene_memory_json(m) ==
          json{{"yardstick", "compressed"}, {"before", 150}, {"after", 60}, {"budget", 40}, {"fits", false}});
    CHECK(scene_memory_json(scene_memory(meshes, BvhYardstick::embree, 0, true)) ==
          json{{"yardstick", "embree"}, {"before", 150}, {"after", 60}, {"estimated", true}});

    // Read back (lsnif merge sums a library's again on the settings its shards recorded).
    for (const SceneMemory& written : {m, scene_memory(meshes, BvhYardstick::embree, 0, true),
                                       scene_memory(meshes, BvhYardstick::embree, 0, false)}) {
        const auto read = scene_memory_from_json(scene_memory_json(written));
        REQUIRE_MESSAGE(read.ok(), read.error());
        CHECK(read->yardstick == written.yardstick);
        CHECK(read->before == written.before);
        CHECK(read->after == written.after);
        CHECK(read->budget == written.budget);
        CHECK(read->estimated == written.estimated);
    }
    json unknown = scene_memory_json(m);
    unknown["yardstick"] = "bvh4";
    CHECK(scene_memory_from_json(unknown).error() == "yardstick: not a BVH yardstick: bvh4");
    json no_fits = scene_memory_json(m);
    no_fits.erase("fits");
    CHECK(scene_memory_from_json(no_fits).error() == "fits: goes with budget, and only with it");
    json negative = scene_memory_json(m);
    negative["after"] = -1;
    CHECK(scene_memory_from_json(negative).error() == "after: not a whole number in range");
    CHECK(scene_memory_from_json(json()).error() == "not an object");
}
