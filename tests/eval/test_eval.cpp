// `lsnif eval` on a real conversion (CGAL's dragon, smoke preset): both tracers, run-time
// instance transforms, camera/light changes without re-conversion, and bad inputs.
#include <doctest/doctest.h>

#include <lsnif/converter/convert.hpp>
#include <lsnif/eval/bench.hpp>
#include <lsnif/eval/eval.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/scene/scene.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>

using namespace lsnif::eval;
using lsnif::converter::convert;
using lsnif::converter::ConvertOptions;
using lsnif::converter::ConvertResult;
using lsnif::render::EvalScene;
using lsnif::render::TraceHit;
using lsnif::render::TraceProfile;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

const std::string kDragon = std::string(LSNIF_TEST_MESH_DIR) + "/ChineseDragon-10kv.off";
const std::string kArmadillo = std::string(LSNIF_TEST_MESH_DIR) + "/armadillo.off";

// One smoke conversion of the dragon, forced complex, shared by the cases below.
const fs::path& converted_dragon() {
    static const fs::path dir = [] {
        const fs::path p = fs::path(LSNIF_TEST_WORK_DIR) / "eval_dragon";
        fs::remove_all(p);
        ConvertOptions o;
        o.inputs = {kDragon};
        o.outdir = p.string();
        o.preset = "smoke";
        o.threads = 2;
        o.seed = 3;
        o.force_complex = {"ChineseDragon-10kv"};
        const ConvertResult r = convert(o);
        REQUIRE_MESSAGE(r.ok(), (r.errors.empty() ? "" : r.errors[0]));
        REQUIRE(r.manifest["meshes"][0]["class"] == "complex");
        return p;
    }();
    return dir;
}

std::string file_bytes(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    return {std::istreambuf_iterator<char>(in), {}};
}

// Rays from a sphere around `box` aimed at random points inside it (the "outside" family).
std::vector<lsnif_ray> rays_at_box(const std::array<float, 6>& b, std::size_t n, std::uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    const float c[3] = {0.5f * (b[0] + b[3]), 0.5f * (b[1] + b[4]), 0.5f * (b[2] + b[5])};
    const float r = std::sqrt((b[3] - b[0]) * (b[3] - b[0]) + (b[4] - b[1]) * (b[4] - b[1]) +
                              (b[5] - b[2]) * (b[5] - b[2]));
    std::vector<lsnif_ray> rays(n);
    for (auto& ray : rays) {
        const float z = 2.0f * u(rng) - 1.0f, phi = 6.2831853f * u(rng), s = std::sqrt(1.0f - z * z);
        const float o[3] = {c[0] + r * s * std::cos(phi), c[1] + r * s * std::sin(phi), c[2] + r * z};
        const float t[3] = {b[0] + u(rng) * (b[3] - b[0]), b[1] + u(rng) * (b[4] - b[1]),
                            b[2] + u(rng) * (b[5] - b[2])};
        ray = {{o[0], o[1], o[2]}, 0.0f, {t[0] - o[0], t[1] - o[1], t[2] - o[2]}, INFINITY};
    }
    return rays;
}

// Fraction of rays on which the hybrid tracer agrees with the reference about hit/miss.
double agreement(const EvalScene& ref_scene, const EvalScene& hyb_scene, const std::vector<lsnif_ray>& rays) {
    std::vector<TraceHit> a(rays.size()), b(rays.size());
    ref_scene.closest(false, rays, a);
    hyb_scene.closest(true, rays, b);
    std::size_t same = 0;
    for (std::size_t i = 0; i < rays.size(); ++i) same += (a[i].instance >= 0) == (b[i].instance >= 0);
    return double(same) / double(rays.size());
}

}  // namespace

TEST_CASE("hybrid tracing applies the instance transform at run time, like Embree does") {
    EvalOptions o;
    o.outdir = converted_dragon().string();
    std::string err;
    const auto at_origin = load_scene(o, err);
    REQUIRE_MESSAGE(at_origin, err);
    REQUIRE(at_origin->lsnif_instance_count() == 1);

    // Rotated 90 degrees about y, scaled by 2.5, moved far away: a transform with every part.
    o.instance_transforms = {{0u,
                              {0.0f, 0.0f, 2.5f, 400.0f,   //
                               0.0f, 2.5f, 0.0f, -120.0f,  //
                               -2.5f, 0.0f, 0.0f, 75.0f}}};
    const auto moved = load_scene(o, err);
    REQUIRE_MESSAGE(moved, err);
    const auto box = moved->instance_bounds(0);
    const auto rays = rays_at_box(box, 4000, 11);

    // Same placement in both tracers: the network agrees with Embree on most rays (the
    // smoke model is small; the default preset measures ~97 % on these rays).
    const double same_place = agreement(*moved, *moved, rays);
    MESSAGE("hit/miss agreement, moved instance: " << same_place);
    CHECK(same_place > 0.85);
    // Control: the hybrid of the un-moved scene sees nothing where the moved dragon is, so
    // agreement falls to the reference's miss rate. If the transform were ignored (or
    // applied inverted) in the hybrid, the first check would look like this one.
    std::vector<TraceHit> ref(rays.size());
    moved->closest(false, rays, ref);
    std::size_t ref_hits = 0;
    for (const auto& h : ref) ref_hits += h.instance >= 0;
    const double control = agreement(*moved, *at_origin, rays);
    CHECK(ref_hits > rays.size() / 5);
    CHECK(control < same_place - 0.15);

    // Distances and normals come back in world space: compare where both hit.
    std::vector<TraceHit> hyb(rays.size());
    moved->closest(true, rays, hyb);
    // The smoke model's normals are poor (~70 deg held out), so normals are judged against
    // a control: the same normals left in object space (as if the hybrid forgot A^-T; for
    // this A that is (-n_z, n_y, n_x) up to scale) must be clearly worse.
    auto deg = [](const std::array<float, 3>& a, const std::array<float, 3>& b) {
        const float c =
            (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) /
            std::sqrt((a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) * (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]));
        return std::acos(std::clamp(c, -1.0f, 1.0f)) * 57.29578f;
    };
    std::vector<float> dt, angle, untransformed;
    for (std::size_t i = 0; i < rays.size(); ++i)
        if (ref[i].instance >= 0 && hyb[i].instance >= 0) {
            const float len = std::sqrt(rays[i].dir[0] * rays[i].dir[0] + rays[i].dir[1] * rays[i].dir[1] +
                                        rays[i].dir[2] * rays[i].dir[2]);
            dt.push_back(std::fabs(ref[i].t - hyb[i].t) * len);
            angle.push_back(deg(ref[i].normal, hyb[i].normal));
            untransformed.push_back(
                deg(ref[i].normal, {-hyb[i].normal[2], hyb[i].normal[1], hyb[i].normal[0]}));
        }
    REQUIRE(dt.size() > 100);
    std::nth_element(dt.begin(), dt.begin() + dt.size() / 2, dt.end());
    std::nth_element(angle.begin(), angle.begin() + angle.size() / 2, angle.end());
    std::nth_element(untransformed.begin(), untransformed.begin() + untransformed.size() / 2,
                     untransformed.end());
    const float diag =
        std::sqrt((box[3] - box[0]) * (box[3] - box[0]) + (box[4] - box[1]) * (box[4] - box[1]) +
                  (box[5] - box[2]) * (box[5] - box[2]));
    MESSAGE("median distance error " << 100.0f * dt[dt.size() / 2] / diag
                                     << " % of the world box diagonal, median normal error "
                                     << angle[angle.size() / 2] << " deg");
    CHECK(dt[dt.size() / 2] < 0.05f * diag);
    MESSAGE("median normal error with the normals left in object space "
            << untransformed[untransformed.size() / 2] << " deg");
    CHECK(angle[angle.size() / 2] < untransformed[untransformed.size() / 2] - 10.0f);

    // Occlusion queries agree too, and a segment that ends before the object is never
    // occluded by it (tmax is honoured by both tracers).
    std::vector<std::uint8_t> occ_ref(rays.size()), occ_hyb(rays.size());
    moved->occluded(false, rays, occ_ref);
    moved->occluded(true, rays, occ_hyb);
    std::size_t same_occ = 0;
    for (std::size_t i = 0; i < rays.size(); ++i) same_occ += occ_ref[i] == occ_hyb[i];
    CHECK(double(same_occ) / rays.size() > 0.85);
    auto short_rays = rays;
    for (auto& r : short_rays) r.tmax = 0.05f;  // origins are a diagonal away from the box
    moved->occluded(true, short_rays, occ_hyb);
    CHECK(std::count(occ_hyb.begin(), occ_hyb.end(), 1) == 0);
}

namespace {

// render_and_compare(o) into a fresh LSNIF_TEST_WORK_DIR/images (o.images_dir is set), which
// must succeed.
EvalResult render_into(EvalOptions& o, const std::string& images) {
    o.images_dir = (fs::path(LSNIF_TEST_WORK_DIR) / images).string();
    fs::remove_all(o.images_dir);
    EvalResult r = render_and_compare(o);
    REQUIRE_MESSAGE(r.ok(), (r.errors.empty() ? "" : r.errors[0]));
    return r;
}

}  // namespace

TEST_CASE("eval renders, compares with FLIP, and camera and light change without re-conversion") {
    const fs::path dir = converted_dragon();
    const json manifest = json::parse(file_bytes(dir / "manifest.json"));
    const fs::path asset = dir / manifest["meshes"][0]["lsnif"]["file"].get<std::string>();
    const std::string asset_before = file_bytes(asset), manifest_before = file_bytes(dir / "manifest.json");

    EvalOptions o;
    o.outdir = dir.string();
    o.width = 96;
    o.height = 72;
    o.ao_samples = 4;
    o.threads = 2;
    const EvalResult a = render_into(o, "eval_images_a");
    const EvalReport& ra = *a.report;
    CHECK(ra.lsnif_instances == 1);
    // The dragon is the only mesh, so its pixels are the frame's covered ones.
    CHECK(ra.lsnif_pixels > 96 * 72 / 20);
    CHECK(ra.lsnif_pixels < 96 * 72);
    double separate = 0;
    for (int e = 0; e < lsnif::render::kEffects; ++e) {
        INFO(lsnif::render::kEffectNames[e]);
        const lsnif::render::EffectComparison& im = ra.hybrid.effect[e];
        CHECK(im.flip.mean >= 0.0);
        CHECK(im.flip.mean <= 1.0);
        CHECK(im.flip.max <= 1.0);
        // Background pixels are identical in both renders: the error sits on the object.
        REQUIRE(im.flip_lsnif_pixels);
        CHECK(im.flip_lsnif_pixels->mean > im.flip.mean);
        CHECK(im.flip_lsnif_pixels->mean <= im.flip.max);
        REQUIRE(im.files.size() == 3);  // reference, hybrid, FLIP
        for (const std::string& f : im.files) CHECK(fs::file_size(fs::path(o.images_dir) / f) > 100);
        if (e != lsnif::render::kCombined) separate += im.flip.mean / 3;
    }
    // The network is not exact: some pixel differs somewhere, but the picture is the same.
    CHECK(ra.hybrid.flip_mean > 0.0);
    CHECK(ra.hybrid.flip_mean < 0.2);
    CHECK(ra.hybrid.flip_mean == doctest::Approx(separate));  // the combined image is extra
    // report.json is the report's one JSON form, the one --json prints.
    const json written = json::parse(file_bytes(fs::path(o.images_dir) / "report.json"));
    CHECK(written == eval_report_json(ra));
    CHECK(written["lsnif_pixels"] == ra.lsnif_pixels);
    CHECK(written["images"]["ao"]["flip_mean"].get<double>() ==
          ra.hybrid.effect[lsnif::render::kAo].flip.mean);
    CHECK(written["all_neural"]["time_ratio"].get<double>() == ra.neural_time_ratio());
    CHECK(written["secondary_profile"]["hybrid"]["ao"]["reader_rays"] ==
          ra.hybrid_profile[1].box_hits);  // families in kRayFamilyNames order: shadow, ao, reflection
    CHECK(eval_report_text(ra).find("  combined   FLIP mean") != std::string::npos);

    // Surface-leaving rays started half a voxel later (hybrid only): the reference is the
    // same picture, the hybrid one changes, and the report says which setting made it.
    {
        EvalOptions later = o;
        later.surface_tmin_voxels = 0.5f;
        const EvalResult l = render_into(later, "eval_images_later");
        CHECK(l.report->surface_tmin_voxels == 0.5f);
        CHECK(ra.surface_tmin_voxels == 0.0f);
        const fs::path a_dir = o.images_dir, l_dir = later.images_dir;
        CHECK(file_bytes(l_dir / "reference_shadow.png") == file_bytes(a_dir / "reference_shadow.png"));
        CHECK(file_bytes(l_dir / "hybrid_ao.png") != file_bytes(a_dir / "hybrid_ao.png"));
    }

    // The escape rule: each asset's own limit (its manifest's) unless forced; forced off, the
    // reference is the same picture, the report says which, and a limit past the asset's
    // entry points per ray is an error naming the asset.
    {
        CHECK_FALSE(ra.escape_points.has_value());
        CHECK(eval_report_json(ra)["escape_points"] == "asset");
        CHECK(eval_report_json(ra)["embree_route"] == "packets16");
        EvalOptions off = o;
        off.escape_points = 0u;
        const EvalResult e0 = render_into(off, "eval_images_escape_off");
        CHECK(eval_report_json(*e0.report)["escape_points"] == 0);
        CHECK(file_bytes(fs::path(off.images_dir) / "reference_ao.png") ==
              file_bytes(fs::path(o.images_dir) / "reference_ao.png"));
        EvalOptions past = o;
        past.escape_points = 64u;
        past.images_dir = (fs::path(LSNIF_TEST_WORK_DIR) / "eval_images_escape_past").string();
        const EvalResult bad = render_and_compare(past);
        REQUIRE_FALSE(bad.ok());
        CHECK(bad.errors[0].find(".lsnif: escape points 64 exceed the asset's") != std::string::npos);
    }

    // One trace per row instead of the fastest of three: the same pictures byte for byte (the
    // repeats only time), and the report says how the time was taken.
    {
        EvalOptions once = o;
        once.timing_repeats = 1;
        const EvalResult r1 = render_into(once, "eval_images_once");
        CHECK(r1.report->timing_repeats == 1);
        CHECK(ra.timing_repeats == 3);
        CHECK(r1.report->timings.secondary_hybrid > 0.0);
        for (const char* f : {"hybrid_combined.png", "hybrid_ao.png", "reference_reflection.png"})
            CHECK(file_bytes(fs::path(once.images_dir) / f) == file_bytes(fs::path(o.images_dir) / f));
    }

    // A moved camera and light, same assets: different pictures, assets untouched.
    const lsnif::render::Camera c = ra.camera;
    lsnif::render::Camera cam;
    for (int k = 0; k < 3; ++k) {
        cam.target[k] = c.target[k];
        cam.eye[k] = 2.0f * c.target[k] - c.eye[k];  // from the other side
    }
    o.camera = cam;
    o.light = {c.target[0], c.target[1] - 500.0f, c.target[2]};
    const EvalResult b = render_into(o, "eval_images_b");
    CHECK(b.report->camera.eye != ra.camera.eye);
    CHECK(b.report->light != ra.light);
    CHECK(file_bytes(fs::path(o.images_dir) / "reference_shadow.png") !=
          file_bytes(fs::path(LSNIF_TEST_WORK_DIR) / "eval_images_a" / "reference_shadow.png"));
    CHECK(b.report->hybrid.flip_mean < 0.2);
    CHECK(file_bytes(asset) == asset_before);
    CHECK(file_bytes(dir / "manifest.json") == manifest_before);
}

TEST_CASE("a conversion's object views give the same FLIP from Embree's SSE4.2, AVX2 and AVX-512 kernels") {
    // The views decide what ships and their FLIP is written into the asset, so they must not
    // depend on the CPU. Embree scales its t, u and v by an approximate reciprocal whose bits
    // differ per kernel here and per CPU vendor elsewhere (an Intel and an AMD host wrote
    // different assets from one command); the views take only the triangle from Embree and
    // compute the rest themselves (ties between triangles at an edge or vertex decided by
    // base::exact_tied_hit, tested with the ground truth in tests/sampling), so three kernels
    // give the same figures to the last bit.
    const fs::path dir = converted_dragon();
    const json manifest = json::parse(file_bytes(dir / "manifest.json"));
    const std::string asset = file_bytes(dir / manifest["meshes"][0]["lsnif"]["file"].get<std::string>());
    const lsnif::scene::ImportResult imported = lsnif::scene::import_mesh_file(kDragon);
    REQUIRE_MESSAGE(imported.ok(), imported.error);
    const lsnif::scene::Mesh& mesh = imported.scene.meshes.at(0);
    std::vector<std::string> isas = {"avx2", "sse4.2"};
    if (lsnif::format::detected_cpu_features().avx512) isas.push_back("avx512");
    std::vector<lsnif::render::ObjectFlip> flips;
    for (const std::string& isa : isas) {
        CAPTURE(isa);
        lsnif::render::ObjectViewOptions o;
        o.embree_isa = isa;
        o.threads = 2;
        std::string error;
        const auto views =
            lsnif::render::ObjectViews::create(mesh.positions, mesh.indices, mesh.normals, o, error);
        REQUIRE_MESSAGE(views, error);
        const auto flip =
            views->compare(std::span(reinterpret_cast<const std::uint8_t*>(asset.data()), asset.size()));
        REQUIRE_MESSAGE(flip, (flip ? "" : flip.error()));
        flips.push_back(*flip);
    }
    CHECK(flips[0].combined_object > 0);  // the asset is not the mesh: there is an error to compare
    for (std::size_t k = 1; k < flips.size(); ++k) {
        CAPTURE(isas[k]);
        CHECK(flips[k].combined == flips[0].combined);
        CHECK(flips[k].combined_object == flips[0].combined_object);
        CHECK(flips[k].combined_object_p95 == flips[0].combined_object_p95);
    }
}

TEST_CASE("eval errors name the file: no manifest, wrong source geometry") {
    EvalOptions o;
    o.outdir = (fs::path(LSNIF_TEST_WORK_DIR) / "no_such_conversion").string();
    EvalResult r = render_and_compare(o);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].find("manifest.json") != std::string::npos);

    o.outdir = converted_dragon().string();
    o.sources = {kArmadillo};
    o.write_images = false;
    r = render_and_compare(o);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].find("armadillo.off") != std::string::npos);
    CHECK(r.errors[0].find("geometry hash mismatch") != std::string::npos);
}

TEST_CASE("bench memory, rays and convert measure a real conversion against Embree") {
    SceneBenchOptions o;
    o.outdir = converted_dragon().string();
    o.threads = 2;
    o.rays = 8192;
    o.repeats = 1;
    const auto mem = bench_memory(o);
    REQUIRE_MESSAGE(mem.ok(), (mem.ok() ? "" : mem.error()));
    REQUIRE(mem->objects.size() == 1);
    const MemoryObject& m = mem->objects[0];
    CHECK(m.triangles == 19994);
    // The asset's bytes as the manifest records them: the file's, and what a renderer holds
    // once it is open (the fp32 network); the ratios compare the BVHs with the latter.
    const json asset = json::parse(file_bytes(converted_dragon() / "manifest.json"))["meshes"][0]["lsnif"];
    CHECK(m.lsnif_file_bytes == asset["bytes"].get<std::uint64_t>());
    CHECK(m.lsnif_resident_bytes == asset["resident_bytes"].get<std::uint64_t>());
    CHECK(m.lsnif_resident_bytes > m.lsnif_file_bytes);
    // The fp32 network holds the weights once, in fp16; a reduced arithmetic adds its packing.
    CHECK(m.lsnif_resident_bytes_here >= m.lsnif_resident_bytes);
    CHECK(m.ratio_embree_over_resident() ==
          doctest::Approx(double(m.embree_bvh_bytes) / double(m.lsnif_resident_bytes)));
    CHECK(m.ratio_bvh8_over_resident() ==
          doctest::Approx(double(m.bvh8_compressed_bytes_estimate) / double(m.lsnif_resident_bytes)));
    CHECK(m.embree_bvh_bytes > 100000u);  // ~1.4 MB for 20k triangles
    // An 8-wide tree over 20k triangles in leaves of <= 3: at least n/3/8 inner nodes,
    // fewer than the triangle count.
    CHECK(double(m.bvh8_inner_nodes) > 19994.0 / 24.0);
    CHECK(m.bvh8_inner_nodes < 19994u);
    CHECK(m.bvh8_compressed_bytes_estimate == 80 * m.bvh8_inner_nodes);
    CHECK(mem->total.lsnif_resident_bytes == m.lsnif_resident_bytes);
    CHECK(mem->total.embree_bvh_bytes == m.embree_bvh_bytes);
    // --json: the keys scripts/bench_table and the investigations read, with the struct's values.
    const json mj = bench_json(*mem);
    CHECK(mj["benchmark"] == "memory");
    CHECK(mj["outdir"] == o.outdir);
    CHECK(mj.contains("yardstick"));
    REQUIRE(mj["objects"].size() == 1);
    const json& mo = mj["objects"][0];
    for (const char* key :
         {"name", "triangles", "instances", "lsnif_file_bytes", "lsnif_resident_bytes",
          "lsnif_resident_bytes_here", "arithmetic_here", "embree_bvh_bytes", "embree_device_bytes",
          "bvh8_inner_nodes", "bvh8_leaves", "bvh8_compressed_bytes_estimate", "ratio_embree_over_resident",
          "ratio_bvh8_over_resident", "ratio_embree_over_file"})
        CHECK_MESSAGE(mo.contains(key), key);
    CHECK(mo.size() == 15);
    CHECK(mo["triangles"] == 19994);
    CHECK(mo["lsnif_resident_bytes"] == asset["resident_bytes"]);
    CHECK(mo["ratio_embree_over_resident"].get<double>() == m.ratio_embree_over_resident());
    for (const char* key :
         {"lsnif_file_bytes", "lsnif_resident_bytes", "embree_bvh_bytes", "bvh8_compressed_bytes_estimate",
          "ratio_embree_over_resident", "ratio_bvh8_over_resident"})
        CHECK_MESSAGE(mj["total"].contains(key), key);
    CHECK(mj["total"].size() == 6);

    const auto rays = bench_rays(o);
    REQUIRE_MESSAGE(rays.ok(), (rays.ok() ? "" : rays.error()));
    REQUIRE(rays->objects.size() == 1);
    const RaysObject& r = rays->objects[0];
    CHECK(r.rays == 8192);
    CHECK(r.lsnif_rays_per_second > 0.0);
    CHECK(r.ratio_lsnif_over_rtcintersect1() > 0.0);
    CHECK(r.hit_agreement > 0.75);  // the smoke model is small
    CHECK(bench_text(*rays).find("ChineseDragon-10kv") != std::string::npos);
    const json rj = bench_json(*rays);
    CHECK(rj["benchmark"] == "rays");
    CHECK(rj["outdir"] == o.outdir);
    REQUIRE(rj["objects"].size() == 1);
    const json& ro = rj["objects"][0];
    for (const char* key : {"name", "triangles", "rays", "threads", "lsnif_rays_per_second",
                            "rtcintersect1_rays_per_second", "rtcintersect16_rays_per_second",
                            "ratio_lsnif_over_rtcintersect1", "ratio_lsnif_over_rtcintersect16",
                            "time_ratio_lsnif_over_rtcintersect1", "hit_agreement", "lsnif_arithmetic"})
        CHECK_MESSAGE(ro.contains(key), key);
    CHECK(ro.size() == 12);
    CHECK(ro["rays"] == 8192);
    CHECK(ro["hit_agreement"].get<double>() == r.hit_agreement);

    ConvertOptions c;
    c.inputs = {kDragon};
    c.outdir = (fs::path(LSNIF_TEST_WORK_DIR) / "bench_convert").string();
    fs::remove_all(c.outdir);
    c.preset = "smoke";
    c.threads = 2;
    c.force_complex = {"ChineseDragon-10kv"};
    const auto conv = bench_convert(c);
    REQUIRE_MESSAGE(conv.ok(), (conv.ok() ? "" : conv.error()));
    for (const char* stage : {"classify", "voxelize", "sample", "train", "evaluate", "write"})
        CHECK_MESSAGE(conv->stage_totals.count(stage) == 1, stage);
    double sum = conv->import_seconds;
    for (const auto& [k, v] : conv->stage_totals) sum += v;
    CHECK(conv->wall_seconds >= sum * 0.99);
    const json cj = bench_json(*conv);
    CHECK(cj["benchmark"] == "convert");
    CHECK(cj["preset"] == "smoke");
    CHECK(cj["threads"] == 2);
    CHECK(cj["wall_seconds"].get<double>() == conv->wall_seconds);
    CHECK(cj["run_timings"] == json{{"import", conv->import_seconds}});
    CHECK(cj["stage_totals"].size() == conv->stage_totals.size());
    for (const auto& [k, v] : conv->stage_totals) CHECK(cj["stage_totals"][k].get<double>() == v);
    REQUIRE(cj["objects"].size() == conv->objects.size());
    const json& co = cj["objects"][0];
    CHECK(co["name"] == "ChineseDragon-10kv");
    CHECK(co["class"] == "complex");
    CHECK(co["triangles"] == 19994);
    CHECK(co["timings"].contains("train"));
    CHECK(co.size() == 4);

    o.outdir = (fs::path(LSNIF_TEST_WORK_DIR) / "no_such_conversion").string();
    const auto missing = bench_memory(o);
    REQUIRE(!missing.ok());
    CHECK(missing.error().find("manifest.json") != std::string::npos);
}

namespace {

// The slab test written plainly, as the reference for the tracer's vectorized one: whether
// ray r meets box b within [tmin, tmax], an axis whose slab distances are NaN unconstrained,
// a ray starting inside with tmin <= 0 <= tmax meeting it at 0.
bool reaches(const lsnif_ray& r, const std::array<float, 6>& b) {
    bool inside = true;
    for (int a = 0; a < 3; ++a) inside = inside && r.org[a] >= b[a] && r.org[a] <= b[a + 3];
    if (inside && r.tmin <= 0.0f && r.tmax >= 0.0f) return true;
    float t0 = r.tmin, t1 = r.tmax;
    for (int a = 0; a < 3; ++a) {
        float tn = (b[a] - r.org[a]) / r.dir[a], tf = (b[a + 3] - r.org[a]) / r.dir[a];
        if (tn > tf) std::swap(tn, tf);
        if (!(tn <= tf)) continue;
        t0 = std::max(t0, tn);
        t1 = std::min(t1, tf);
    }
    return t0 <= t1;
}

}  // namespace

TEST_CASE("a trace profile counts the rays each tracer gave the reader, and only those that reach a box") {
    EvalOptions o;
    o.outdir = converted_dragon().string();
    std::string err;
    const auto scene = load_scene(o, err);
    REQUIRE_MESSAGE(scene, err);
    const auto box = scene->instance_bounds(0);
    // Rays at the box, the same rays turned away (they reach it only from inside), segments
    // ending before it, and rays along the box's faces and edges with direction components
    // of zero (the slab test's NaN cases).
    std::vector<lsnif_ray> rays = rays_at_box(box, 600, 5);
    for (std::size_t i = 0; i < 600; i += 3) {
        lsnif_ray away = rays[i];
        for (float& d : away.dir) d = -d;
        rays.push_back(away);
        lsnif_ray shortened = rays[i];
        shortened.tmax = 0.01f;
        rays.push_back(shortened);
    }
    const float mid[3] = {0.5f * (box[0] + box[3]), 0.5f * (box[1] + box[4]), 0.5f * (box[2] + box[5])};
    for (int a = 0; a < 3; ++a)
        for (const float plane : {box[a], box[a + 3], mid[a]}) {
            lsnif_ray r{{mid[0], mid[1], mid[2]}, 0.0f, {0, 0, 0}, INFINITY};
            r.org[a] = plane;
            const int b = (a + 1) % 3;
            r.org[b] = box[b] - 1.0f;  // outside, moving along axis b on the plane
            r.dir[b] = 1.0f;
            rays.push_back(r);
        }
    for (int k = 0; k < 20; ++k) {  // from inside the box, some starting later than 0
        lsnif_ray r = rays[k];
        std::copy(mid, mid + 3, r.org);
        r.tmin = k % 2 ? 0.0f : 0.5f;
        rays.push_back(r);
    }
    std::size_t expected = 0;
    for (const lsnif_ray& r : rays) expected += reaches(r, box);

    std::vector<std::uint8_t> occ(rays.size());
    TraceProfile reference, hybrid;
    scene->occluded(false, rays, occ, &reference);
    scene->occluded(true, rays, occ, &hybrid);
    CHECK(reference.rays == rays.size());
    CHECK(reference.reader_calls == 0);
    CHECK(reference.box_hits == 0);
    CHECK(hybrid.rays == rays.size());
    CHECK(hybrid.box_hits == expected);  // the scene is the dragon alone: nothing occludes first
    CHECK(expected > 300);
    CHECK(expected < rays.size() - 100);
    CHECK(hybrid.reader_calls == (expected + 255) / 256);
    CHECK(hybrid.reader_hits == std::size_t(std::count(occ.begin(), occ.end(), 1)));
    CHECK(hybrid.seconds >= hybrid.embree_seconds + hybrid.reader_seconds);

    std::vector<TraceHit> hits(rays.size());
    TraceProfile closest;
    scene->closest(true, rays, hits, &closest);
    CHECK(closest.box_hits == expected);
    std::size_t hit = 0;
    for (const TraceHit& h : hits) hit += h.instance >= 0;
    CHECK(closest.reader_hits >= hit);  // a reader hit beyond tmax is no hit
    closest += hybrid;
    CHECK(closest.rays == 2 * rays.size());
}

TEST_CASE("Embree's 16-wide packets give the hits and occlusion of single rays, in both tracers") {
    EvalOptions o;
    o.outdir = converted_dragon().string();
    std::string err;
    o.embree_route = lsnif::render::EmbreeRoute::single;
    const auto single = load_scene(o, err);
    REQUIRE_MESSAGE(single, err);
    o.embree_route = lsnif::render::EmbreeRoute::packets16;
    const auto packets = load_scene(o, err);
    REQUIRE_MESSAGE(packets, err);
    // Not a multiple of 16: the last packet has switched-off lanes. Every third ray is a
    // segment ending short of the box, which no route may report as a hit. Embree's packet
    // and single-ray kernels may decide a grazing ray differently: a few in ten thousand may
    // differ, a lane answered for another ray would not.
    std::vector<lsnif_ray> rays = rays_at_box(packets->instance_bounds(0), 4007, 23);
    for (std::size_t i = 0; i < rays.size(); i += 3) rays[i].tmax = 0.01f;
    for (const bool hybrid : {false, true}) {
        CAPTURE(hybrid);
        std::vector<TraceHit> a(rays.size()), b(rays.size());
        single->closest(hybrid, rays, a);
        packets->closest(hybrid, rays, b);
        std::size_t hits = 0, same = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) {
            hits += a[i].instance >= 0;
            same += a[i].instance == b[i].instance &&
                    std::fabs(a[i].t - b[i].t) <= 1e-5f * std::max(1.0f, std::fabs(a[i].t)) &&
                    a[i].normal == b[i].normal;
        }
        CHECK(hits > rays.size() / 5);
        CHECK(same + 4 >= rays.size());
        std::vector<std::uint8_t> oa(rays.size()), ob(rays.size());
        single->occluded(hybrid, rays, oa);
        packets->occluded(hybrid, rays, ob);
        std::size_t same_occ = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) same_occ += oa[i] == ob[i];
        CHECK(same_occ + 4 >= rays.size());
        CHECK(std::size_t(std::count(ob.begin(), ob.end(), 1)) > rays.size() / 5);
    }
}
