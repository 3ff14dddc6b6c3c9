// `lsnif eval`: reference (Embree everywhere) and hybrid (Embree + LSNIF reader) renders of
// a converted scene, compared with FLIP and PSNR (eval.hpp has the contract).
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/text.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/eval/eval.hpp>
#include <lsnif/scene/scene.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>

namespace lsnif::eval {
namespace fs = std::filesystem;
using converter::LoadedManifest;
using converter::MeshClass;
using converter::MeshOutcome;
using nlohmann::json;
using namespace render;

namespace {

// The source scene of every input that converted; an input that failed in convert
// (InputRecord::error) contributed no meshes and stays empty.
bool import_sources(const LoadedManifest& loaded, std::vector<scene::Scene>& scenes, std::string& error) {
    scenes.assign(loaded.sources.size(), {});
    for (std::size_t s = 0; s < loaded.sources.size(); ++s) {
        if (!loaded.inputs[s].ok()) continue;
        auto r = scene::import_scene(loaded.sources[s]);
        if (!r.ok()) {
            error = loaded.path.string() + ": input " + std::to_string(s) + ": " + r.error;
            return false;
        }
        scenes[s] = std::move(r.scene);
    }
    return true;
}

// Every mesh of the manifest, from its source scene, into `builder`: its asset when it is
// complex and shipped one.
bool add_meshes(const LoadedManifest& loaded, const std::vector<scene::Scene>& scenes, const EvalOptions& opt,
                SceneBuilder& builder, std::string& error) {
    const std::string manifest_path = loaded.path.string();
    for (const MeshOutcome& mo : loaded.meshes) {
        const std::size_t input = mo.input, src = mo.source_mesh;
        if (input >= scenes.size() || src >= scenes[input].meshes.size()) {
            error = manifest_path + ": mesh '" + mo.name + "' refers to input " + std::to_string(input) +
                    " mesh " + std::to_string(src) + ", which the source does not have";
            return false;
        }
        const scene::Mesh& sm = scenes[input].meshes[src];
        if (scene::geometry_hash(sm) != mo.geometry_hash) {
            error = loaded.sources[input] + ": mesh '" + sm.name +
                    "' differs from the converted geometry (geometry hash mismatch): re-run lsnif convert";
            return false;
        }
        SceneMesh m{sm.name, sm.positions, sm.indices, sm.normals, {}};
        if (mo.cls() == MeshClass::complex && mo.asset)
            m.asset = (fs::path(opt.outdir) / mo.asset->file).string();
        // The escape rule: the caller's limit, else the one conversion chose for the asset.
        const std::uint32_t escape =
            opt.escape_points.value_or(mo.held_out ? mo.held_out->escape_points : 0u);
        if (!builder.add_mesh(m, {opt.arithmetic, escape, opt.enclosed_rule}, error)) return false;
    }
    return true;
}

// Instance i of the manifest (opt.instance_transforms may override its placement) into
// `builder`.
bool add_instance(std::size_t i, const json& ij, const EvalOptions& opt, const std::string& manifest_path,
                  SceneBuilder& builder, std::string& error) {
    const auto malformed = [&] {
        const json& t = ij.is_object() ? ij.value("transform", json()) : json();
        if (!ij.is_object() || !ij.value("mesh", json()).is_number_unsigned() || !t.is_array() ||
            t.size() != 12)
            return true;
        return std::any_of(t.begin(), t.end(), [](const json& x) { return !x.is_number(); });
    };
    if (malformed() || ij["mesh"].get<std::uint64_t>() >= builder.mesh_count()) {
        error = manifest_path + ": instance " + std::to_string(i) + " is malformed";
        return false;
    }
    std::array<float, 12> transform{};
    for (int k = 0; k < 12; ++k) transform[k] = ij["transform"][k].get<float>();
    for (const auto& [which, m] : opt.instance_transforms)
        if (which == i) transform = m;
    if (!builder.add_instance(ij["mesh"].get<std::uint32_t>(), transform, error)) {
        error = manifest_path + ": " + error;
        return false;
    }
    return true;
}

}  // namespace

std::unique_ptr<EvalScene> load_scene(const EvalOptions& opt, std::string& error) {
    LoadedManifest loaded;
    if (!converter::load_manifest(opt.outdir, opt.sources, loaded, error)) return nullptr;
    const std::string manifest_path = loaded.path.string();
    std::vector<scene::Scene> scenes;
    if (!import_sources(loaded, scenes, error)) return nullptr;
    SceneBuilder builder;
    if (!builder.open(error, opt.embree_route) || !add_meshes(loaded, scenes, opt, builder, error))
        return nullptr;
    const json& insts = loaded.doc["instances"];
    for (std::size_t i = 0; i < insts.size(); ++i)
        if (!add_instance(i, insts[i], opt, manifest_path, builder, error)) return nullptr;
    if (builder.instance_count() == 0) {
        error = manifest_path + ": no instances";
        return nullptr;
    }
    return builder.finish(error);
}

namespace {

// The report's "images": per effect its FLIP, PSNR (null for identical images: infinite),
// FLIP over the LSNIF pixels (null when there are none) and its files.
json comparison_json(const Comparison& c) {
    json per = json::object();
    for (int e = 0; e < kEffects; ++e) {
        const EffectComparison& x = c.effect[e];
        json j = {{"flip_mean", x.flip.mean},
                  {"flip_median", x.flip.median},
                  {"flip_p95", x.flip.p95},
                  {"flip_max", x.flip.max}};
        j["psnr_db"] = std::isfinite(x.psnr_db) ? json(x.psnr_db) : json(nullptr);
        j["flip_mean_lsnif_pixels"] = x.flip_lsnif_pixels ? json(x.flip_lsnif_pixels->mean) : json(nullptr);
        j["flip_p95_lsnif_pixels"] = x.flip_lsnif_pixels ? json(x.flip_lsnif_pixels->p95) : json(nullptr);
        if (!x.files.empty())
            j["files"] = {{"reference", x.files[0]}, {"hybrid", x.files[1]}, {"flip", x.files[2]}};
        per[kEffectNames[e]] = j;
    }
    return per;
}

// `text` to `path` through a temporary file and a rename: no half-written file.
bool write_text_atomically(const fs::path& path, const std::string& text, std::string& error) {
    const fs::path tmp = path.string() + ".tmp";
    {
        std::ofstream o(tmp);
        o << text;
        if (!o) {
            error = tmp.string() + ": cannot write";
            std::error_code ec;
            fs::remove(tmp, ec);
            return false;
        }
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        error = path.string() + ": " + ec.message();
        return false;
    }
    return true;
}

// A tracer's profile per ray family, for the report (docs/eval.md "Where the secondary rays'
// time goes"): seconds summed over threads, counts over the frame.
json profile_json(const SecondaryProfile& profile) {
    json j = json::object();
    for (int f = 0; f < kRayFamilies; ++f) {
        const TraceProfile& p = profile[f];
        j[kRayFamilyNames[f]] = {
            {"seconds", p.seconds},
            {"embree_seconds", p.embree_seconds},
            {"reader_seconds", p.reader_seconds},
            {"cull_and_batch_seconds", std::max(0.0, p.seconds - p.embree_seconds - p.reader_seconds)},
            {"rays", p.rays},
            {"reader_rays", p.box_hits},
            {"reader_calls", p.reader_calls},
            {"reader_hits", p.reader_hits}};
    }
    return j;
}

}  // namespace

EvalResult render_and_compare(const EvalOptions& opt) {
    EvalResult res;
    std::string err;
    auto scene = load_scene(opt, err);
    if (!scene) {
        res.errors.push_back(err);
        return res;
    }
    if (opt.width == 0 || opt.height == 0 || opt.width > 8192 || opt.height > 8192) {
        res.errors.push_back("image size " + std::to_string(opt.width) + "x" + std::to_string(opt.height) +
                             " out of range (1..8192)");
        return res;
    }
    const std::uint32_t threads = base::resolve_threads(opt.threads);
    const View view = make_view(opt, scene->world_bounds());

    // Primary visibility twice: from the meshes (the hybrid render's, as a rasterizer would)
    // and through the assets (the all-neural render's); each timed at its fastest of the
    // repeats, alternating.
    double primary_seconds = INFINITY, neural_primary_seconds = INFINITY;
    GBuffer gb, neural_gb;
    for (std::uint32_t r = 0; r < std::max(1u, opt.timing_repeats); ++r) {
        gb = render_primary(*scene, view, threads);
        primary_seconds = std::min(primary_seconds, gb.trace_seconds);
        neural_gb = render_primary(*scene, view, threads, true);
        neural_primary_seconds = std::min(neural_primary_seconds, neural_gb.trace_seconds);
    }
    const std::vector<float> tmins = surface_tmins(*scene, opt.surface_tmin_voxels);
    const BothImages both = render_secondary(*scene, gb, view, opt, tmins, threads);
    const EffectImages& reference = both.reference;
    const EffectImages& hybrid = both.hybrid;
    const EffectImages neural =
        render_secondary(*scene, neural_gb, view, opt, tmins, threads, Tracers::hybrid).hybrid;

    const fs::path images = opt.images_dir.empty() ? fs::path(opt.outdir) / "eval" : fs::path(opt.images_dir);
    if (opt.write_images) {
        std::error_code ec;
        fs::create_directories(images, ec);
        if (ec) {
            res.errors.push_back(images.string() + ": cannot create directory: " + ec.message());
            return res;
        }
    }
    Comparison compared, compared_neural;
    const std::vector<std::uint8_t> lsnif_pixels = lsnif_pixel_mask(gb, *scene);
    // The all-neural render's LSNIF pixels: where the mesh or the asset is what the camera sees.
    const std::vector<std::uint8_t> neural_pixels =
        mask_union(lsnif_pixels, lsnif_pixel_mask(neural_gb, *scene));
    if (!compare_effects(reference, hybrid, view, lsnif_pixels, images, opt.write_images, compared, err) ||
        !compare_effects(reference, neural, view, neural_pixels, images, opt.write_images, compared_neural,
                         err, "neural")) {
        res.errors.push_back(err);
        return res;
    }
    EvalReport report;
    report.memory = scene->asset_memory();
    report.width = view.W;
    report.height = view.H;
    report.ao_samples = std::max(1u, opt.ao_samples);
    report.ao_radius = opt.ao_radius * view.diag;
    report.surface_tmin_voxels = opt.surface_tmin_voxels;
    report.escape_points = opt.escape_points;
    report.embree_route = opt.embree_route;
    report.enclosed_rule = opt.enclosed_rule;
    report.timing_repeats = std::max(1u, opt.timing_repeats);
    report.camera = view.cam;
    report.light = view.light;
    report.instances = scene->instance_count();
    report.lsnif_instances = scene->lsnif_instance_count();
    report.hybrid = std::move(compared);
    report.neural = std::move(compared_neural);
    report.lsnif_pixels = std::size_t(std::count(lsnif_pixels.begin(), lsnif_pixels.end(), 1));
    report.neural_lsnif_pixels = std::size_t(std::count(neural_pixels.begin(), neural_pixels.end(), 1));
    report.timings = {primary_seconds, neural_primary_seconds, reference.trace_seconds, hybrid.trace_seconds,
                      neural.trace_seconds};
    report.reference_profile = reference.profile;
    report.hybrid_profile = hybrid.profile;
    report.images_dir = images.string();
    if (opt.write_images &&
        !write_text_atomically(images / "report.json", eval_report_json(report).dump(2) + "\n", err)) {
        res.errors.push_back(err);
        return res;
    }
    res.report = std::move(report);
    return res;
}

double EvalReport::secondary_time_ratio() const {
    return timings.secondary_reference > 0 ? timings.secondary_hybrid / timings.secondary_reference : 0.0;
}

double EvalReport::neural_time_ratio() const {
    const double reference = timings.primary + timings.secondary_reference;
    return reference > 0 ? (timings.primary_neural + timings.secondary_neural) / reference : 0.0;
}

json eval_report_json(const EvalReport& r) {
    json j;
    j["lsnif_arithmetic"] = lsnif_arithmetic_string(r.memory.arithmetic);
    j["width"] = r.width;
    j["height"] = r.height;
    j["ao_samples"] = r.ao_samples;
    j["ao_radius"] = r.ao_radius;
    j["surface_tmin_voxels"] = r.surface_tmin_voxels;
    j["escape_points"] = r.escape_points ? json(*r.escape_points) : json("asset");
    j["timing_repeats"] = r.timing_repeats;
    j["embree_route"] = render::embree_route_name(r.embree_route);
    j["enclosed_rule"] = r.enclosed_rule;
    j["camera"] = {{"eye", r.camera.eye},
                   {"target", r.camera.target},
                   {"up", r.camera.up},
                   {"fov_deg", r.camera.fov_deg}};
    j["light"] = r.light;
    j["instances"] = r.instances;
    j["lsnif_instances"] = r.lsnif_instances;
    // Resident bytes of the opened assets (lsnif_info.decoded_bytes) against Embree's BVHs of
    // the meshes they replace, measured in this render's device.
    j["memory"] = {{"lsnif_resident_bytes", r.memory.lsnif_resident_bytes},
                   {"bvh_bytes_replaced", r.memory.bvh_bytes_replaced}};
    j["images"] = comparison_json(r.hybrid);
    j["flip_mean"] = r.hybrid.flip_mean;
    j["lsnif_pixels"] = r.lsnif_pixels;
    j["all_neural"] = {{"images", comparison_json(r.neural)},
                       {"flip_mean", r.neural.flip_mean},
                       {"lsnif_pixels", r.neural_lsnif_pixels},
                       {"time_ratio", r.neural_time_ratio()}};
    j["timings"] = {{"primary", r.timings.primary},
                    {"primary_neural", r.timings.primary_neural},
                    {"secondary_reference", r.timings.secondary_reference},
                    {"secondary_hybrid", r.timings.secondary_hybrid},
                    {"secondary_neural", r.timings.secondary_neural}};
    j["secondary_time_ratio"] = r.secondary_time_ratio();
    j["secondary_profile"] = {{"reference", profile_json(r.reference_profile)},
                              {"hybrid", profile_json(r.hybrid_profile)}};
    j["images_dir"] = r.images_dir;
    return j;
}

namespace {

// The mean FLIP over a comparison's LSNIF pixels, or "none" when there are none.
std::string lsnif_pixels_mean(const EffectComparison& c) {
    return c.flip_lsnif_pixels ? std::to_string(c.flip_lsnif_pixels->mean) : std::string("none");
}

}  // namespace

std::string eval_report_text(const EvalReport& r) {
    std::string out;
    out += base::printed("rendered %ux%u, %zu instances (%zu through LSNIF), images in %s\n", r.width,
                         r.height, r.instances, r.lsnif_instances, r.images_dir.c_str());
    for (int e = 0; e < kEffects; ++e) {
        const EffectComparison& c = r.hybrid.effect[e];
        const std::string psnr = std::isfinite(c.psnr_db) ? std::to_string(c.psnr_db) : std::string("inf");
        out +=
            base::printed("  %-10s FLIP mean %.4f (median %.4f, p95 %.4f; on LSNIF pixels %s)  PSNR %s dB\n",
                          kEffectNames[e], c.flip.mean, c.flip.median, c.flip.p95,
                          lsnif_pixels_mean(c).c_str(), psnr.c_str());
    }
    out += base::printed(
        "  overall    FLIP mean %.4f (shadow, ao, reflection); %zu LSNIF pixels; secondary-ray time "
        "hybrid/reference %.2f (Embree route %s)\n",
        r.hybrid.flip_mean, r.lsnif_pixels, r.secondary_time_ratio(),
        render::embree_route_name(r.embree_route));
    const EffectComparison& nc = r.neural.effect[kCombined];
    out += base::printed(
        "  all-neural (primary rays through the assets too): combined FLIP %.4f over the frame, %s over "
        "%zu LSNIF pixels; time all-neural/reference %.2f\n",
        nc.flip.mean, lsnif_pixels_mean(nc).c_str(), r.neural_lsnif_pixels, r.neural_time_ratio());
    out +=
        "  secondary rays' time (seconds over all threads; hybrid = Embree on the meshes + box tests and "
        "batching "
        "+ the reader):\n";
    for (int f = 0; f < kRayFamilies; ++f) {
        const TraceProfile& ref = r.reference_profile[f];
        const TraceProfile& h = r.hybrid_profile[f];
        const double cull = std::max(0.0, h.seconds - h.embree_seconds - h.reader_seconds);
        out += base::printed(
            "    %-10s reference %.3f | hybrid %.3f = %.3f + %.3f + %.3f; %llu of %llu rays to the reader in "
            "%llu calls (%.0f per call), %.1f %% of them hit\n",
            kRayFamilyNames[f], ref.seconds, h.seconds, h.embree_seconds, cull, h.reader_seconds,
            (unsigned long long)h.box_hits, (unsigned long long)h.rays, (unsigned long long)h.reader_calls,
            h.reader_calls ? double(h.box_hits) / double(h.reader_calls) : 0.0,
            h.box_hits ? 100.0 * double(h.reader_hits) / double(h.box_hits) : 0.0);
    }
    return out;
}

}  // namespace lsnif::eval
