// Each stage of `lsnif convert` on its own (converter/convert/src/convert_stages.hpp), on CGAL's
// ChineseDragon-10kv (real data) and on meshes built here to break one rule at a time. The
// whole pipeline is tested end to end in test_convert.cpp.
#include <doctest/doctest.h>
#include "../test_data.hpp"

#include <lsnif/converter/manifest.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include "convert_stages.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <map>

using namespace lsnif;
using namespace lsnif::converter;
using namespace lsnif::converter::stages;

namespace {

const std::string kDragon = std::string(LSNIF_TEST_MESH_DIR) + "/ChineseDragon-10kv.off";

fs::path fresh_dir(const std::string& name) {
    return lsnif::test::fresh_dir(LSNIF_TEST_WORK_DIR, name);
}

scene::Mesh dragon() {
    auto r = scene::import_scene(kDragon);
    REQUIRE_MESSAGE(r.ok(), r.error);
    REQUIRE(r.scene.meshes.size() == 1);
    return r.scene.meshes[0];
}

// A run of `preset` with two threads; `opt` must outlive the Run.
Run make_run(const ConvertOptions& opt, const fs::path& outdir) {
    Preset p;
    std::string error;
    REQUIRE_MESSAGE(resolve_preset(opt, p, error), error);
    return Run{opt, p, 2, outdir, {}, nullptr};
}

ConvertOptions options(const std::string& preset) {
    ConvertOptions o;
    o.preset = preset;
    o.threads = 2;
    o.seed = 5;
    return o;
}

}  // namespace

TEST_CASE("resolve_preset applies every command-line override, and names the presets it knows") {
    ConvertOptions o = options("smoke");
    o.steps = 123;
    o.batch_size = 256;
    o.log2_table_size = 11;
    o.max_points = 5;
    o.grid_resolution = 16;
    o.hidden_width = 32;
    o.gate_min_visibility = 0.5;
    Preset p;
    std::string error;
    REQUIRE(resolve_preset(o, p, error));
    CHECK(p.name == "smoke");
    CHECK(p.train.steps == 123);
    CHECK(p.train.batch_size == 256);
    CHECK(p.model.log2_table_size == 11);
    CHECK(p.model.max_points == 5);
    CHECK(p.model.grid_resolution == 16);
    for (std::uint32_t w : p.model.hidden_width) CHECK(w == 32);
    CHECK(p.gate.min_visibility == 0.5);
    // The default preset sizes to the target; --fixed-model trains one model to the end.
    CHECK(p.sizing.explore_smaller);
    CHECK(p.sizing.quantize);
    CHECK(p.target_stop.consecutive > 0);
    o.fixed_model = true;
    REQUIRE(resolve_preset(o, p, error));
    CHECK_FALSE(p.sizing.explore_smaller);
    CHECK_FALSE(p.sizing.quantize);
    CHECK(p.target_stop.consecutive == 0);
    // --no-give-up: no validation check can abort training.
    CHECK(p.early_abort.min_samples < std::numeric_limits<std::uint64_t>::max());
    o.no_give_up = true;
    REQUIRE(resolve_preset(o, p, error));
    CHECK(p.early_abort.min_samples == std::numeric_limits<std::uint64_t>::max());

    o.preset = "turbo";
    CHECK_FALSE(resolve_preset(o, p, error));
    CHECK(error.find("unknown preset 'turbo'") == 0);
    for (const auto& name : preset_names()) CHECK(error.find(name) != std::string::npos);
}

TEST_CASE("range_problem: single precision models boxes from 1e-15 to 1e15, nothing outside") {
    CHECK(range_problem({{-1.f, -1.f, -1.f}, {1.f, 1.f, 1.f}}).empty());
    CHECK(range_problem({{1e6f, 1e6f, 1e6f}, {1e6f + 1.f, 1e6f + 1.f, 1e6f + 1.f}}).empty());
    CHECK_FALSE(range_problem({{0.f, 0.f, 0.f}, {1e-20f, 1e-20f, 1e-20f}}).empty());
    CHECK_FALSE(range_problem({{-1e16f, 0.f, 0.f}, {1e16f, 1.f, 1.f}}).empty());
    CHECK_FALSE(range_problem({{1e20f, 0.f, 0.f}, {1e20f * 1.0001f, 1.f, 1.f}}).empty());
}

TEST_CASE("classify sizes the hash tables to beat the BVH, unless forced, and measures the mesh") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("default");
    o.log2_table_size = 18;  // the 8-bit 2^18 model's estimate is more than half the dragon's BVH
    const Run run = make_run(o, fresh_dir("stages_classify"));
    MeshOutcome out;
    const auto c = classify(run, mesh, false, out);
    REQUIRE(c.has_value());
    REQUIRE(c->source);
    CHECK(c->desc.log2_table_size < run.preset.model.log2_table_size);  // a 10k-vertex mesh: smaller tables
    CHECK(c->desc.log2_table_size >= run.preset.classify.min_log2_table_size);
    CHECK(c->desc.box_min == c->box.min);
    REQUIRE(out.stats.has_value());
    // Both yardsticks measured; the compressed BVH (inner nodes only) is the smaller one, and
    // the tables were halved until the asset, held in memory, beats the yardstick's BVH twice
    // (or the smallest table was reached).
    CHECK(out.stats->bvh.embree > 0);
    CHECK(out.stats->bvh.compressed > 0);
    CHECK(out.stats->bvh.compressed < out.stats->bvh.embree);
    CHECK(out.stats->resident_estimate > 0);
    CHECK((2 * out.stats->resident_estimate <= out.stats->bvh.embree ||
           c->desc.log2_table_size == run.preset.classify.min_log2_table_size));
    CHECK(out.stats->components >= 1);
    CHECK(out.stats->area_ratio > 0);
    CHECK(out.stats->box_min == c->box.min);
    std::size_t outside = 0;  // the padded box strictly holds every vertex
    for (std::size_t v = 0; v < mesh.vertex_count(); ++v)
        for (int a = 0; a < 3; ++a)
            outside +=
                !(mesh.positions[v * 3 + a] > c->box.min[a] && mesh.positions[v * 3 + a] < c->box.max[a]);
    CHECK(outside == 0);

    // On the compressed yardstick the BVH is smaller, so the tables are at most as large.
    ConvertOptions oc = o;
    oc.bvh_yardstick = BvhYardstick::compressed;
    const Run compressed_run = make_run(oc, fresh_dir("stages_classify_compressed"));
    MeshOutcome compressed_out;
    const auto cc = classify(compressed_run, mesh, false, compressed_out);
    REQUIRE(cc.has_value());
    CHECK(cc->desc.log2_table_size <= c->desc.log2_table_size);
    CHECK(cc->bvh.compressed == c->bvh.compressed);  // one build thread: the same node count

    MeshOutcome forced_out;
    const auto forced = classify(run, mesh, true, forced_out);
    REQUIRE(forced.has_value());
    CHECK(forced->forced);
    CHECK(forced->desc.log2_table_size == run.preset.model.log2_table_size);
}

TEST_CASE("classify keeps a mesh it cannot model as BVH, with the reason") {
    const ConvertOptions o = options("smoke");
    const Run run = make_run(o, fresh_dir("stages_classify_bad"));
    scene::Mesh far;  // one triangle at 1e20: outside single precision's modelling range
    far.name = "far";
    far.positions = {1e20f, 0, 0, 1e20f * 1.0001f, 0, 0, 1e20f, 1, 0};
    far.normals = {0, 0, 1, 0, 0, 1, 0, 0, 1};
    far.indices = {0, 1, 2};
    MeshOutcome out;
    CHECK_FALSE(classify(run, far, false, out).has_value());
    CHECK(out.decision == Decision::not_modelable);
    CHECK(out.cls() == MeshClass::simple);
    REQUIRE(out.reasons.size() == 1);
    CHECK(out.reasons[0].find("outside the range LSNIF models in single precision") != std::string::npos);

    scene::Mesh nan = far;  // a non-finite vertex: the box cannot be computed
    nan.positions[4] = std::numeric_limits<float>::quiet_NaN();
    MeshOutcome nan_out;
    CHECK_FALSE(classify(run, nan, false, nan_out).has_value());
    CHECK(nan_out.decision == Decision::not_modelable);
    REQUIRE(nan_out.reasons.size() == 1);
    CHECK(nan_out.reasons[0].find("cannot bound the mesh") == 0);
}

TEST_CASE(
    "voxelize_mesh and worth_an_lsnif: occupancy recorded; the memory rule decides, --complex overrides") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("default");
    Run run = make_run(o, fresh_dir("stages_memory"));
    MeshOutcome out;
    const auto c = classify(run, mesh, false, out);
    REQUIRE(c.has_value());
    const auto occ = voxelize_mesh(run, mesh, *c, out);
    REQUIRE(occ.has_value());
    REQUIRE(out.stats->occupied_fraction.has_value());
    const double fraction = *out.stats->occupied_fraction;
    CHECK(fraction > 0.01);
    CHECK(fraction < 0.5);
    CHECK(occ->count() == std::uint64_t(std::llround(fraction * double(c->desc.voxel_count()))));

    CHECK(worth_an_lsnif(run, mesh, *c, out));  // sized to beat the BVH by min_memory_ratio
    run.preset.classify.min_memory_ratio = 1e9;
    MeshOutcome strict;
    CHECK_FALSE(worth_an_lsnif(run, mesh, *c, strict));
    CHECK(strict.decision == Decision::no_memory_benefit);
    REQUIRE(strict.reasons.size() == 2);
    CHECK(strict.reasons[1].find("below the") != std::string::npos);

    // On the compressed yardstick (0.30 MB for this 20k-triangle dragon) no asset halves the
    // memory, and the reason names the yardstick.
    run.preset.classify.min_memory_ratio = 2.0;
    run.preset.classify.yardstick = BvhYardstick::compressed;
    MeshOutcome compressed;
    CHECK_FALSE(worth_an_lsnif(run, mesh, *c, compressed));
    CHECK(compressed.decision == Decision::no_memory_benefit);
    REQUIRE(!compressed.reasons.empty());
    CHECK(compressed.reasons[0].find("compressed BVH") == 0);

    MeshOutcome forced_out;
    const auto forced = classify(run, mesh, true, forced_out);
    REQUIRE(forced.has_value());
    CHECK(worth_an_lsnif(run, mesh, *forced, forced_out));
    CHECK(forced_out.reasons.back().find("forced complex") == 0);
}

// The settings table drives what a batch records and what a Ninja step passes on
// (settings_arguments): every setting that changes a result must survive that round trip,
// or a step computes another key than its plan ("plan again").
TEST_CASE("every setting survives settings_arguments and back, and every mesh setting changes the key") {
    // An example value per row: a row without one fails here, so a new setting brings its check.
    const std::map<std::string, std::string> example = {{"--preset", "fast"},
                                                        {"--seed", "9"},
                                                        {"--arithmetic", "machine"},
                                                        {"--complex", "ChineseDragon-10kv"},
                                                        {"--simple", "armadillo"},
                                                        {"--gate-visibility", "50"},
                                                        {"--steps", "7"},
                                                        {"--batch", "128"},
                                                        {"--log2-table", "11"},
                                                        {"--first-log2-table", "13"},
                                                        {"--max-points", "5"},
                                                        {"--grid", "16"},
                                                        {"--hidden", "24"},
                                                        {"--max-grid", "64"},
                                                        {"--no-ray-inputs", ""},
                                                        {"--target", "90,2,20"},
                                                        {"--memory-budget", "64M"},
                                                        {"--bvh-yardstick", "compressed"},
                                                        {"--memory-ratio", "1.5"},
                                                        {"--fixed-model", ""},
                                                        {"--no-give-up", ""},
                                                        {"--keep-inactive", ""},
                                                        {"--threads", "3"},
                                                        {"--jobs", "2"},
                                                        {"--dry-run", ""},
                                                        {"--target-flip", "0.05"},
                                                        {"--accept", "rays"},
                                                        {"--view-seed", "7"},
                                                        {"--gate-flip", "0.1"},
                                                        {"--cache", "http://127.0.0.1:9/cache"},
                                                        {"--cache-local", "local-cache"},
                                                        {"--cache-read-only", ""},
                                                        {"--cache-timeout", "2.5"}};
    const scene::Mesh mesh = dragon();
    const fs::path dir = fresh_dir("settings_round_trip");
    const ConvertOptions base = options("smoke");
    const auto key_of = [&](const ConvertOptions& o) {
        const Run run = make_run(o, dir);
        return asset_key(run, mesh, run.preset.model);
    };
    const std::string base_key = key_of(base);
    const bool bf16_here = arithmetic_id(Arithmetic::machine) != arithmetic_id(Arithmetic::canonical);
    std::size_t mesh_rows = 0;
    for (const Setting& s : settings_table()) {
        const std::string name = long_name(s);
        CAPTURE(name);
        REQUIRE_MESSAGE(example.count(name), "no example value for " << name);
        ConvertOptions given = base;
        std::string error, warning;
        REQUIRE_MESSAGE(s.set(given, example.at(name), error, warning), error);
        CHECK(warning.empty());
        const std::vector<std::string> args = settings_arguments(given);
        // What a step rebuilds from the recorded arguments alone (run settings are its own).
        ConvertOptions rebuilt;
        rebuilt.threads = given.threads;
        rebuilt.jobs = given.jobs;
        rebuilt.dry_run = given.dry_run;
        REQUIRE_MESSAGE(apply_settings_arguments(args, rebuilt, error), error);
        CHECK(settings_arguments(rebuilt) == args);
        CHECK(mesh_settings_key(rebuilt) == mesh_settings_key(given));
        CHECK(settings_json(rebuilt) == settings_json(given));
        CHECK(key_of(rebuilt) == key_of(given));
        switch (s.scope) {
            case SettingScope::mesh:
                ++mesh_rows;
                if (name != "--arithmetic" || bf16_here) CHECK(key_of(given) != base_key);
                break;
            case SettingScope::report:  // recorded and in the record's cache key, never in the asset's
                CHECK(args != settings_arguments(base));
                CHECK(key_of(given) == base_key);
                CHECK(report_settings_key(given) != report_settings_key(base));
                break;
            case SettingScope::scene:  // recorded, but a mesh's key does not hold the scene's choices
                CHECK(args != settings_arguments(base));
                CHECK(key_of(given) == base_key);
                break;
            case SettingScope::run:  // neither recorded nor keyed
                CHECK(args == settings_arguments(base));
                CHECK(key_of(given) == base_key);
                break;
        }
    }
    CHECK(mesh_rows >= 15);
    // Bad values and unknown options are errors that name the option.
    ConvertOptions o;
    std::string error;
    CHECK_FALSE(apply_settings_arguments({"--steps", "0"}, o, error));
    CHECK(error.find("--steps '0'") != std::string::npos);
    CHECK_FALSE(apply_settings_arguments({"--colour", "red"}, o, error));
    CHECK(error.find("--colour") != std::string::npos);
    CHECK_FALSE(apply_settings_arguments({"--seed"}, o, error));
    // Percentages everywhere: --gate-visibility as --target. Its earlier fractions are still
    // read, with a warning.
    const Setting& gate = *std::find_if(settings_table().begin(), settings_table().end(),
                                        [](const Setting& s) { return long_name(s) == "--gate-visibility"; });
    for (const auto& [text, deprecated] : {std::pair{"95", false}, std::pair{"0.95", true}}) {
        ConvertOptions g;
        std::string e, warning;
        REQUIRE(gate.set(g, text, e, warning));
        CHECK(g.gate_min_visibility == doctest::Approx(0.95));
        CHECK(warning.empty() != deprecated);
    }
    ConvertOptions g;
    std::string e, warning;
    CHECK_FALSE(gate.set(g, "101", e, warning));
    CHECK(gate.set(g, "0", e, warning));  // 0: ships whatever trained (tests, packages)
    CHECK(g.gate_min_visibility == 0.0);
}

TEST_CASE("asset_key changes with the geometry and every setting that changes the weights, and only then") {
    const scene::Mesh mesh = dragon();
    const ConvertOptions o = options("smoke");
    const Run run = make_run(o, fresh_dir("stages_key"));
    format::ModelDesc desc = run.preset.model;
    const std::string key = asset_key(run, mesh, desc);
    CHECK(asset_key(run, mesh, desc) == key);

    scene::Mesh moved = mesh;
    moved.positions[0] += 1e-3f;
    CHECK(asset_key(run, moved, desc) != key);

    ConvertOptions o2 = o;
    o2.seed = 6;
    CHECK(asset_key(make_run(o2, run.outdir), mesh, desc) != key);
    // Threads never change a result, so they are not part of the key; the arithmetic is,
    // where the machine arithmetic differs from the canonical one (a CPU with bf16 products).
    Run other_threads = make_run(o, run.outdir);
    other_threads.threads = 1;
    CHECK(asset_key(other_threads, mesh, desc) == key);
    ConvertOptions machine = o;
    machine.arithmetic = Arithmetic::machine;
    const bool bf16_here = arithmetic_id(Arithmetic::machine) != arithmetic_id(Arithmetic::canonical);
    CHECK((asset_key(make_run(machine, run.outdir), mesh, desc) != key) == bf16_here);
    ConvertOptions o3 = o;
    o3.steps = run.preset.train.steps + 1;
    CHECK(asset_key(make_run(o3, run.outdir), mesh, desc) != key);
    format::ModelDesc smaller = desc;
    smaller.log2_table_size -= 1;
    CHECK(asset_key(run, mesh, smaller) != key);
    // The target and the sizing rules decide which steps and which size ship.
    ConvertOptions o4 = o;
    o4.target.visibility = 0.99;  // any value but the default's
    CHECK(asset_key(make_run(o4, run.outdir), mesh, desc) != key);
    ConvertOptions o5 = o;
    o5.fixed_model = true;
    CHECK(asset_key(make_run(o5, run.outdir), mesh, desc) != key);
    ConvertOptions o6 = o;
    o6.no_give_up = true;
    CHECK(asset_key(make_run(o6, run.outdir), mesh, desc) != key);
    ConvertOptions o7 = o;
    o7.keep_inactive = true;
    CHECK(asset_key(make_run(o7, run.outdir), mesh, desc) != key);
    // The normal loss's shape and smoothing.
    Run cosine = make_run(o, run.outdir);
    cosine.preset.train.normal_loss = lsnif::trainer::NormalLoss::cosine;
    CHECK(asset_key(cosine, mesh, desc) != key);
    Run smoother = make_run(o, run.outdir);
    smoother.preset.train.normal_chord_epsilon *= 2;
    CHECK(asset_key(smoother, mesh, desc) != key);
    // Where the output goes does not change the weights.
    CHECK(asset_key(make_run(o, fresh_dir("stages_key_elsewhere")), mesh, desc) == key);
}

TEST_CASE("reusable_metrics: an asset is reused only when it is intact and was written for the same key") {
    const fs::path dir = fresh_dir("stages_reuse");
    ConvertOptions o = options("smoke");
    o.inputs = {kDragon};
    o.outdir = dir.string();
    o.force_complex = {"ChineseDragon-10kv"};
    o.gate_min_visibility = 0;
    const ConvertResult r = convert(o);
    REQUIRE_MESSAGE(r.ok(), (r.errors.empty() ? "" : r.errors[0]));
    const json report = convert_report_json(r);
    const json& m = report["meshes"][0];
    REQUIRE(m["class"] == "complex");
    const fs::path asset = dir / m["lsnif"]["file"].get<std::string>();
    REQUIRE(fs::exists(asset));

    const Run run = make_run(o, dir);
    MeshOutcome rec;
    const scene::Mesh mesh = dragon();
    const auto c = classify(run, mesh, true, rec);
    REQUIRE(c.has_value());
    const std::string key = asset_key(run, mesh, c->desc);
    const auto metrics = reusable_metrics(asset, key);
    REQUIRE(metrics.has_value());
    // The metrics read back are the ones the report shows, every field.
    CHECK(held_out_json(*metrics) == m["metrics"]);
    CHECK(metrics->gate.passed);
    CHECK_FALSE(reusable_metrics(asset, key + "x").has_value());
    CHECK_FALSE(reusable_metrics(dir / "absent.lsnif", key).has_value());

    const fs::path torn = dir / "torn.lsnif";
    fs::copy_file(asset, torn);
    fs::resize_file(torn, fs::file_size(torn) / 2);
    CHECK_FALSE(reusable_metrics(torn, key).has_value());
}

TEST_CASE("write_manifest writes the whole document or reports why, never a partial file") {
    const fs::path dir = fresh_dir("stages_manifest");
    const json doc = {{"format", "test"}, {"meshes", json::array({1, 2, 3})}};
    CHECK(write_manifest(dir / "out", doc).empty());
    std::ifstream f(dir / "out" / "manifest.json");
    CHECK(json::parse(f) == doc);
    for (const auto& e : fs::directory_iterator(dir / "out")) CHECK(e.path().filename() == "manifest.json");

    std::ofstream(dir / "file") << "x";  // a file where the output directory should be
    const std::string error = write_manifest(dir / "file" / "sub", doc);
    CHECK(error.find((dir / "file" / "sub").string()) == 0);
    CHECK_FALSE(fs::exists(dir / "file" / "sub"));
}

namespace {

// Classify, voxelize and draw the measuring rays of the dragon for `run`, forced or not.
struct Prepared {
    Candidate c;
    voxelize::Occupancy occ;
    MeasureRays rays;
};
Prepared prepare(const Run& run, const scene::Mesh& mesh, MeshOutcome& out) {
    auto c = classify(run, mesh, false, out);
    REQUIRE(c.has_value());
    auto occ = voxelize_mesh(run, mesh, *c, out);
    REQUIRE(occ.has_value());
    MeasureRays rays = draw_measure_rays(run, mesh, *c, out);
    return {std::move(*c), std::move(*occ), std::move(rays)};
}

// The manifest's `candidates` of a sizing, as the manifest writes them (outcome_json).
json candidates_json(const Sized& sized) {
    MeshOutcome o;
    for (const Option& opt : sized.options)
        o.candidates.push_back(candidate_record(opt, sized.rungs[opt.rung], sized.options.size()));
    return outcome_json(o)["candidates"];
}

}  // namespace

TEST_CASE("size_to_target walks down the ladder while each size meets the target, within one budget") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("smoke");
    std::string error;
    REQUIRE(parse_target("50,50,90", o.target, error));  // met at the first checks of every size
    o.target.flip = 1;                                   // the rays' target alone
    Run run = make_run(o, fresh_dir("stages_ladder"));
    run.preset.classify.min_log2_table_size = 10;  // the smoke model's 2^12 rows, then 2^11 and 2^10
    run.preset.gate = {0.5, 0.3, 50.0, 90.0};      // training aims at the stricter of target and gate
    MeshOutcome rec;
    Prepared p = prepare(run, mesh, rec);
    REQUIRE(p.c.desc.log2_table_size == 12);
    const Sized sized = size_to_target(run, mesh, p.c, p.occ, p.rays, rec);
    const json candidates = candidates_json(sized);
    REQUIRE_MESSAGE(sized.rungs.size() == 3, candidates.dump());
    REQUIRE(sized.options.size() == 6);  // each size in fp16 and 8-bit
    REQUIRE(candidates.size() == 6);
    std::uint32_t budget = run.preset.train.steps, steps_trained = 0;
    for (std::size_t i = 0; i < 3; ++i) {
        const json& fp16 = candidates[2 * i];
        const json& u8 = candidates[2 * i + 1];
        CAPTURE(fp16.dump());
        CHECK(fp16["log2_table_size"] == 12 - i);
        CHECK(u8["log2_table_size"] == 12 - i);
        CHECK(fp16["grid"] == "fp16");
        CHECK(u8["grid"] == "u8_affine");
        CHECK(sized.options[2 * i + 1].model.desc.grid_encoding == format::GridEncoding::u8_affine);
        CHECK(u8["bytes"].get<std::uint64_t>() < fp16["bytes"].get<std::uint64_t>());
        CHECK(fp16.contains("validation"));  // the training's curve, once per size
        CHECK_FALSE(u8.contains("validation"));
        CHECK(fp16["target_met"] == true);
        // TargetStop: two checks in a row; check k of a rung comes at the first step at or
        // past k tenths of its own budget.
        const std::uint32_t checks = run.preset.validation_checks;
        CHECK(fp16["steps"] == (2 * budget + checks - 1) / checks);
        CHECK(fp16["steps_planned"] == budget);  // what the larger sizes left of the budget
        CHECK(fp16["stopped"] == "the validation curve met the target");
        if (i > 0)
            CHECK(fp16["bytes"].get<std::uint64_t>() < candidates[2 * i - 2]["bytes"].get<std::uint64_t>());
        budget -= fp16["steps"].get<std::uint32_t>();
        steps_trained += fp16["steps"].get<std::uint32_t>();
    }
    CHECK(steps_trained <= run.preset.train.steps);
    // The smallest that meets the target: the 8-bit 2^10 model, if quantization kept it
    // at the target, else the fp16 one.
    REQUIRE(sized.chosen.has_value());
    const std::size_t expected = sized.options[5].target_met ? 5 : 4;
    CHECK(*sized.chosen == expected);
    CHECK(candidates[expected]["outcome"] == "chosen: the smallest of 6 candidates that meets the target");
    CHECK(candidates[0]["outcome"] == "meets the target, but a smaller candidate does too");

    // --fixed-model: the preset's model, fp16, trained to the end of the budget.
    ConvertOptions fixed_opt = o;
    fixed_opt.fixed_model = true;
    Run fixed = make_run(fixed_opt, run.outdir);
    fixed.preset.classify.min_log2_table_size = 10;
    fixed.preset.gate = run.preset.gate;
    const Sized one = size_to_target(fixed, mesh, p.c, p.occ, p.rays, rec);
    const json one_candidates = candidates_json(one);
    REQUIRE(one.options.size() == 1);
    CHECK(one_candidates[0]["grid"] == "fp16");
    CHECK(one_candidates[0]["steps"] == fixed.preset.train.steps);
    CHECK(one.chosen == 0u);
}

TEST_CASE(
    "size_to_target: a target no size meets ships the largest through the gate, and tries nothing smaller") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("smoke");
    std::string error;
    REQUIRE(parse_target("99.9,0.01,1", o.target, error));
    Run run = make_run(o, fresh_dir("stages_ladder_missed"));
    run.preset.classify.min_log2_table_size = 10;
    MeshOutcome rec;
    Prepared p = prepare(run, mesh, rec);
    const Sized sized = size_to_target(run, mesh, p.c, p.occ, p.rays, rec);
    REQUIRE(sized.rungs.size() == 1);
    REQUIRE(sized.options.size() == 2);
    const json candidates = candidates_json(sized);
    CHECK(candidates[0]["target_met"] == false);
    CHECK(candidates[0]["steps"] == run.preset.train.steps);  // nothing stopped it
    // The largest size, in its smaller encoding when that passes the gate.
    REQUIRE(sized.chosen.has_value());
    CHECK(*sized.chosen == (candidates[1]["gate_passed"].get<bool>() ? 1u : 0u));
    CHECK(sized.options[*sized.chosen].outcome == CandidateOutcome::chosen_passes_gate);
    CHECK(candidates[*sized.chosen]["outcome"] ==
          "chosen: no candidate meets the target; the largest passes the gate");

    // Below the gate too, rays alone judging: nothing ships.
    run.preset.gate.min_visibility = 0.9999;
    run.preset.gate.accept = Acceptance::rays;
    const Sized none = size_to_target(run, mesh, p.c, p.occ, p.rays, rec);
    const json none_candidates = candidates_json(none);
    CHECK_FALSE(none.chosen.has_value());
    CHECK(none_candidates[0]["outcome"] == "fails the gate");
}

TEST_CASE("size_to_target climbs from its first size only after a near miss, with a whole budget") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("smoke");
    std::string error;
    REQUIRE(parse_target("99.9,0.01,1", o.target, error));  // no size meets it
    o.first_log2_table_size = 11;                           // below the smoke model's 2^12
    Run run = make_run(o, fresh_dir("stages_climb"));
    run.preset.classify.min_log2_table_size = 10;
    MeshOutcome rec;
    Prepared p = prepare(run, mesh, rec);
    REQUIRE(p.c.desc.log2_table_size == 12);
    CHECK(first_rung_log2(run.preset, 12) == 11);

    // Far from the target (the default margins): the first size is all that trains, and it
    // ships through the gate.
    const Sized far = size_to_target(run, mesh, p.c, p.occ, p.rays, rec);
    const json far_candidates = candidates_json(far);
    REQUIRE_MESSAGE(far.rungs.size() == 1, far_candidates.dump());
    CHECK(far_candidates[0]["log2_table_size"] == 11);
    CHECK_FALSE(near_target(far.options[0].decided.pooled, effective_target(run.opt.target, run.preset.gate),
                            run.preset.sizing));

    // Margins wide enough that the miss counts as near: 2^12 trains with a budget of its own,
    // and the largest size trained is what ships through the gate.
    run.preset.sizing.climb_visibility = 1.0;
    run.preset.sizing.climb_distance_factor = 1e6;
    run.preset.sizing.climb_normal_deg = 180.0;
    MeshOutcome climbed_rec;
    const Sized climbed = size_to_target(run, mesh, p.c, p.occ, p.rays, climbed_rec);
    const json candidates = candidates_json(climbed);
    REQUIRE_MESSAGE(climbed.rungs.size() == 2, candidates.dump());
    CHECK(candidates[0]["log2_table_size"] == 11);
    CHECK(candidates[2]["log2_table_size"] == 12);  // one size up, never past triage's
    CHECK(candidates[0]["steps"] == run.preset.train.steps);
    CHECK(candidates[2]["steps_planned"] == run.preset.train.steps);
    REQUIRE(climbed.chosen.has_value());
    CHECK(climbed.options[*climbed.chosen].model.desc.log2_table_size == 12);
    CHECK(climbed.options[*climbed.chosen].outcome == CandidateOutcome::chosen_passes_gate);
    REQUIRE_FALSE(climbed_rec.reasons.empty());
    CHECK(climbed_rec.reasons.back().find("2^11 rows ended near the target") != std::string::npos);
    CHECK(climbed_rec.reasons.back().find("trained again at 2^12") != std::string::npos);
}

TEST_CASE("near_target: each metric within its climb margin") {
    const Target target;  // 98.5 %, 0.6 %, 8 deg
    const Sizing rule;    // 0.5 points, 1.5x, 2 deg
    samples::FamilyMetrics m;
    m.visibility_accuracy = 0.9844;  // CGAL's armadillo at 2^16 rows
    m.distance_median_pct = 0.31;
    m.normal_median_deg = 7.8;
    CHECK(near_target(m, target, rule));
    m.visibility_accuracy = 0.979;  // 0.6 points short
    CHECK_FALSE(near_target(m, target, rule));
    m.visibility_accuracy = 0.9844;
    m.normal_median_deg = 10.5;  // 2.5 degrees over
    CHECK_FALSE(near_target(m, target, rule));
    m.normal_median_deg = 9.9;
    CHECK(near_target(m, target, rule));
    m.distance_median_pct = 0.95;  // over 1.5x
    CHECK_FALSE(near_target(m, target, rule));
}

TEST_CASE("falls_behind: a smaller size is given up when the larger one's later gain cannot close its gap") {
    const Target target{0.97, 1.0, 15.0};  // the default before the coarse levels
    const TargetStop stop;                 // +0.3 points
    const Sizing rule;                     // 1 point of slack
    // The blob's default-preset curve at 2^17 rows (docs/model.md "Sizing to the target").
    const std::vector<ValidationPoint> larger = {
        {240, 0.9573, 0, 0}, {480, 0.9689, 0, 0}, {720, 0.9741, 0, 0}, {960, 0.9752, 0, 0}};
    auto at = [&](std::uint32_t step, double vis) {
        return falls_behind({step, vis, 0, 0}, larger, target, stop, rule);
    };
    // At step 240 the larger gained 1.79 points afterwards: 94.4 + 1.79 + 1 < 97.3.
    const std::optional<RuleMiss> behind = at(240, 0.944);
    REQUIRE(behind);
    CHECK(behind->bound == Bound::larger_rung);
    CHECK(behind->step == 240);
    CHECK(behind->value == doctest::Approx(0.944));
    CHECK(behind->larger_gain == doctest::Approx(0.0179));
    CHECK(behind->limit == doctest::Approx(0.973));
    CHECK(describe(*behind) ==
          "validation visibility 94.40 % at step 240; the larger model gained 1.79 points after that step, "
          "short of the 97.30 % needed");
    CHECK_FALSE(at(240, 0.9455));  // 94.55 + 1.79 + 1 >= 97.3
    CHECK_FALSE(at(288, 0.9473));  // the blob's 2^16 rung at step 288: it went on to meet the target
    CHECK(at(720, 0.961));         // gain 0.11 after 720
    CHECK_FALSE(at(720, 0.9625));
    CHECK_FALSE(at(1200, 0.90));  // beyond the larger curve: not judged
    CHECK_FALSE(at(100, 0.50));   // before its first check: not judged
    CHECK_FALSE(falls_behind({240, 0.5, 0, 0}, {}, target, stop, rule));  // the first rung
}

TEST_CASE("shard_owners deals the costliest candidates first to the least loaded shard, in any input order") {
    ConvertOptions o = options("smoke");
    o.shard_count = 3;
    const Run run = make_run(o, fresh_dir("shard_owners"));
    // One mesh whose triangles alone outweigh two small candidates, six small ones, and a
    // mesh that was decided in triage (no shard converts it).
    std::vector<scene::Mesh> meshes(8);
    for (std::size_t i = 0; i < meshes.size(); ++i) {
        meshes[i].name = "m" + std::to_string(i);
        meshes[i].positions = {0, 0, 0, 1, 0, 0, 0, 1, float(i)};
        meshes[i].indices.assign(3 * (i == 0 ? 20'000'000 : 1000 + i), 0);
    }
    std::vector<Triaged> triaged(meshes.size());
    for (std::size_t i = 0; i < meshes.size(); ++i) {
        triaged[i].mesh = &meshes[i];
        triaged[i].source = "library.glb";
        if (i == 7)
            triaged[i].decided = true;
        else
            triaged[i].candidate.emplace();
    }
    REQUIRE(estimated_cost_ms(run, triaged[0]) > 2 * estimated_cost_ms(run, triaged[1]));
    const std::vector<std::uint32_t> owner = shard_owners(run, triaged);
    CHECK(owner[7] == 0);
    std::array<int, 4> count{};
    for (std::size_t i = 0; i < 7; ++i) {
        REQUIRE((owner[i] >= 1 && owner[i] <= 3));
        ++count[owner[i]];
    }
    // The big one gets a shard to itself; the six small ones share the other two evenly.
    CHECK(count[owner[0]] == 1);
    CHECK(count[1] + count[2] + count[3] == 7);
    for (std::uint32_t s = 1; s <= 3; ++s)
        if (s != owner[0]) CHECK(count[s] == 3);
    // The same split from the candidates in reverse order: every shard computes it alone.
    std::vector<Triaged> reversed;
    for (std::size_t i = triaged.size(); i-- > 0;) reversed.push_back(std::move(triaged[i]));
    const std::vector<std::uint32_t> again = shard_owners(run, reversed);
    for (std::size_t i = 0; i < owner.size(); ++i) CHECK(again[owner.size() - 1 - i] == owner[i]);
}

namespace {

// The reader's fp32 answers for the samples' rays.
std::vector<format::Hit> answers(const format::ModelData& model, std::span<const samples::Sample> samples) {
    const format::Runtime rt = format::make_runtime(model, format::MlpArithmetic::fp32);
    std::vector<format::Ray> rays;
    for (const samples::Sample& s : samples) rays.push_back(s.ray);
    std::vector<format::Hit> hits(rays.size());
    format::intersect(rt, rays, hits);
    return hits;
}

std::size_t same_answers(const std::vector<format::Hit>& a, const std::vector<format::Hit>& b) {
    std::size_t n = 0;
    for (std::size_t i = 0; i < a.size(); ++i)
        n += a[i].hit == b[i].hit && a[i].t == b[i].t && a[i].normal[0] == b[i].normal[0] &&
             a[i].normal[1] == b[i].normal[1] && a[i].normal[2] == b[i].normal[2];
    return n;
}

// Makes hidden neuron j of layer k output zero for every input: zero weights, bias -1.
void silence(format::ModelData& m, std::uint32_t k, std::uint32_t j) {
    const std::uint32_t in = m.desc.layer_shape(k).second;
    std::fill_n(m.weights[k].begin() + std::size_t(j) * in, in, format::float_to_half(0.0f));
    m.biases[k][j] = format::float_to_half(-1.0f);
}

}  // namespace

TEST_CASE(
    "pruning removes exactly the neurons no validation ray activates, and the network answers those rays "
    "as before") {
    const scene::Mesh mesh = dragon();
    ConvertOptions o = options("smoke");
    o.keep_inactive = true;  // train_rung ships the whole network; the stages run by hand below
    const Run run = make_run(o, fresh_dir("stages_prune"));
    MeshOutcome rec;
    Prepared p = prepare(run, mesh, rec);
    const Trained t =
        train_rung(run, mesh, p.c, p.c.desc, p.occ, p.rays, run.preset.train.steps, RungRole::first, {}, rec);
    CHECK(t.pruned.empty());
    REQUIRE(t.model.desc.hidden_width == run.preset.model.hidden_width);
    const std::size_t layers = t.model.desc.hidden_width.size();
    REQUIRE(layers == 2);

    format::ModelData model = t.model;
    silence(model, 0, 3);
    silence(model, 1, 0);
    silence(model, 1, 17);
    const auto active = active_neurons(model, p.rays.validation, 2);
    CHECK(active_neurons(model, p.rays.validation, 1) == active);  // whatever the threads
    REQUIRE(active.size() == layers);
    std::vector<std::uint32_t> inactive(layers, 0);
    for (std::size_t k = 0; k < layers; ++k) {
        REQUIRE(active[k].size() == model.desc.hidden_width[k]);
        for (const std::uint8_t a : active[k]) inactive[k] += a ? 0 : 1;
    }
    CHECK(active[0][3] == 0);
    CHECK(active[1][0] == 0);
    CHECK(active[1][17] == 0);
    MESSAGE("inactive neurons beside the silenced ones: " << inactive[0] - 1 << ", " << inactive[1] - 2);

    format::ModelData pruned = model;
    const std::vector<std::uint32_t> removed = remove_inactive_neurons(pruned, active);
    CHECK(removed == inactive);
    for (std::size_t k = 0; k < layers; ++k)
        CHECK(pruned.desc.hidden_width[k] == model.desc.hidden_width[k] - inactive[k]);
    CHECK_FALSE(format::validate_model(pruned));
    REQUIRE(format::serialize(pruned).ok());
    CHECK(pruned.desc.parameter_count() < model.desc.parameter_count());
    // Every validation ray gets the same answer, bit for bit: the removed terms were zeros.
    const auto before = answers(model, p.rays.validation), after = answers(pruned, p.rays.validation);
    CHECK(same_answers(before, after) == before.size());

    // Removing a neuron that some ray does activate changes answers: the comparison above
    // can fail.
    auto wrong = active;
    std::size_t last_active = 0;
    for (std::size_t j = 0; j < wrong[1].size(); ++j)
        if (wrong[1][j]) last_active = j;
    wrong[1][last_active] = 0;
    format::ModelData damaged = model;
    remove_inactive_neurons(damaged, wrong);
    CHECK(same_answers(before, answers(damaged, p.rays.validation)) < before.size());

    // A layer no ray activates keeps one neuron (a width is at least 1).
    std::vector<std::vector<std::uint8_t>> none = active;
    std::fill(none[1].begin(), none[1].end(), std::uint8_t(0));
    format::ModelData narrow = model;
    remove_inactive_neurons(narrow, none);
    CHECK(narrow.desc.hidden_width[1] == 1);
    CHECK_FALSE(format::validate_model(narrow));

    // In the pipeline (the preset's default): train_rung ships the pruned network and says so.
    const ConvertOptions prune_opt = options("smoke");
    const Run pruning = make_run(prune_opt, run.outdir);
    REQUIRE(pruning.preset.prune_inactive);
    const Trained tp = train_rung(pruning, mesh, p.c, p.c.desc, p.occ, p.rays, run.preset.train.steps,
                                  RungRole::first, {}, rec);
    REQUIRE(tp.pruned.size() == layers);
    const auto natural = active_neurons(t.model, p.rays.validation, 2);
    for (std::size_t k = 0; k < layers; ++k) {
        const auto off = std::uint32_t(std::count(natural[k].begin(), natural[k].end(), std::uint8_t(0)));
        CHECK(tp.pruned[k] == off);  // the same training (same seed, threads), pruned
        CHECK(tp.model.desc.hidden_width[k] == run.preset.model.hidden_width[k] - tp.pruned[k]);
    }
    CHECK(same_answers(answers(t.model, p.rays.validation), answers(tp.model, p.rays.validation)) ==
          p.rays.validation.size());
}
