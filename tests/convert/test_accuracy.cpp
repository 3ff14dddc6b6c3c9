// Accuracy targets of `lsnif convert` on real meshes with the *default*
// preset and automatic classification (the asset that ships, sized to the target):
// held-out rays that reach the network, the three ray families pooled in equal shares,
// meet the default target (visibility accuracy >= 98.5 % within two standard errors of the
// held-out estimate, median distance error <= 0.6 % of the box diagonal, median
// shading-normal error <= 8 degrees), and the surface family's visibility is at least 97.5 %. Every family's
// figures are printed, as is the geometric-normal error.
//
// Every shipped asset's memory and held-out image error are checked against its file. Beyond
// CGAL's scans, two models of sweethome3d-furniture's catalogues: a truck assembly, which
// ships past the gate but short of the target, and a tree, which stays BVH under the
// calibrated image gate. The paper-like dragons composition through `lsnif eval`: the
// combined image against Embree, in the hybrid and the all-neural render. And the bundled
// scene, whose hairball stays BVH under the calibrated image gate.
//
// This converts meshes at full size (minutes of training), so it is registered only in
// optimized builds (label "accuracy"); a sanitized build would take far longer and measure
// nothing different.
#include <doctest/doctest.h>

#include <lsnif/lsnif.h>
#include <lsnif/converter/convert.hpp>
#include <lsnif/eval/eval.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/sampling/sampling.hpp>
#include <lsnif/voxelize/voxelize.hpp>

#include "convert_stages.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "../test_data.hpp"

namespace fs = std::filesystem;
using lsnif::converter::ConvertOptions;
using lsnif::converter::ConvertResult;

namespace {

// Converts one mesh with the default preset and options, as a user would: automatic
// classification, the memory rule and sizing to the default target choose its model (unless
// `forced`: the mesh starts at the preset's model, whatever the memory rule says). Returns
// the mesh's manifest entry.
fs::path accuracy_dir(const std::string& name) {
    return fs::path(LSNIF_TEST_WORK_DIR) / ("accuracy_" + name);
}

nlohmann::json convert_default(const fs::path& file, const std::string& name, bool forced = false) {
    ConvertOptions opt;
    if (forced) opt.force_complex = {name};
    opt.inputs = {file.string()};
    opt.outdir = accuracy_dir(name).string();
    fs::remove_all(opt.outdir);
    opt.preset = "default";
    opt.seed = 1;
    const ConvertResult r = lsnif::converter::convert(opt);
    REQUIRE(r.ok());
    REQUIRE(r.manifest["meshes"].size() == 1);
    return r.manifest["meshes"][0];
}

// Writes a scene with `lsnif_make_example_scene ARGS` into DIR/scene.glb (DIR emptied
// first) and converts it into DIR/out with the default preset, seed 1, forcing the meshes
// named in `complex` to be modelled.
ConvertResult convert_generated(const fs::path& dir, const std::string& args,
                                std::vector<std::string> complex) {
    fs::remove_all(dir);
    fs::create_directories(dir);
    const fs::path glb = dir / "scene.glb";
    const std::string cmd =
        std::string(LSNIF_MAKE_SCENE_EXE) + " --out " + glb.string() + " " + args + " > /dev/null";
    REQUIRE(std::system(cmd.c_str()) == 0);
    ConvertOptions opt;
    opt.inputs = {glb.string()};
    opt.outdir = (dir / "out").string();
    opt.preset = "default";
    opt.seed = 1;
    opt.force_complex = std::move(complex);
    return lsnif::converter::convert(opt);
}

fs::path cgal_mesh(const std::string& file) {
    return fs::path(LSNIF_TEST_MESH_DIR) / file;
}

// sweethome3d-furniture's models, extracted by tests/CMakeLists.txt.
fs::path furniture_mesh(const std::string& model) {
    const fs::path dir = fs::path(LSNIF_TEST_FURNITURE_DIR) / model;
    return dir / (dir.filename().string() + ".obj");
}

void print_families(const nlohmann::json& mesh) {
    const auto& fam = mesh["metrics"]["families"];
    for (const char* f : {"outside", "surface", "interior", "pooled"}) {
        const auto& m = fam[f];
        MESSAGE(mesh["name"].get<std::string>()
                << " " << std::string(f) << ": visibility " << 100 * m["visibility_accuracy"].get<double>()
                << " %, distance " << m["distance_error_median_pct"].get<double>() << " %, normal "
                << m["normal_error_median_deg"].get<double>() << " deg (geometric "
                << m["geometric_normal_error_median_deg"].get<double>() << " deg)");
    }
    MESSAGE("timings (s): " << mesh["timings"].dump());
}

// Standard error of the pooled held-out visibility: the mean of the three families' rates,
// each a binomial estimate over its rays, so var = sum over f of p_f (1 - p_f) / n_f / 9.
double pooled_visibility_standard_error(const nlohmann::json& mesh) {
    double var = 0;
    for (const char* f : {"outside", "surface", "interior"}) {
        const auto& m = mesh["metrics"]["families"][f];
        const double p = m["visibility_accuracy"].get<double>(), n = m["rays"].get<double>();
        var += p * (1 - p) / std::max(n, 1.0) / 9.0;
    }
    return std::sqrt(var);
}

// What the manifest says of a shipped asset holds for its file: a renderer that opens it holds
// resident_bytes (lsnif_info.decoded_bytes with the fp32 network, the most any CPU holds), the
// mesh's memory after conversion is that, and its BVH before is Embree's (the default
// yardstick); its image error on the held-out views is recorded, and an asset shipped by its
// images is within the calibrated image gate on those views too.
void check_shipped_asset(const nlohmann::json& mesh, const fs::path& outdir) {
    REQUIRE(mesh.contains("lsnif"));
    const fs::path asset = outdir / mesh["lsnif"]["file"].get<std::string>();
    lsnif_model* model = nullptr;
    REQUIRE(lsnif_open_file(asset.c_str(), &model, nullptr) == LSNIF_OK);
    REQUIRE(lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_OK);
    lsnif_info info{};
    REQUIRE(lsnif_get_info(model, &info) == LSNIF_OK);
    lsnif_close(model);
    CHECK(mesh["lsnif"]["resident_bytes"] == info.decoded_bytes);
    CHECK(mesh["lsnif"]["bytes"] == info.file_size);
    CHECK(mesh["memory"]["after"] == info.decoded_bytes);
    CHECK(mesh["memory"]["before"] == mesh["stats"]["bvh"]["embree"]);
    REQUIRE(mesh.contains("held_out_images"));
    const double flip = mesh["held_out_images"]["combined_object"].get<double>();
    MESSAGE(mesh["name"].get<std::string>()
            << ": held in memory " << info.decoded_bytes << " bytes (file " << info.file_size
            << ") against an Embree BVH of " << mesh["stats"]["bvh"]["embree"] << " and a compressed one of "
            << mesh["stats"]["bvh"]["compressed"] << "; image error on held-out views " << flip << " (p95 "
            << mesh["held_out_images"]["combined_object_p95"] << "), decision views "
            << mesh["metrics"]["flip"]["combined_object"] << "; ships by " << mesh["metrics"]["gate"]["by"]);
    if (mesh["metrics"]["gate"]["by"] == "images") {
        CHECK(flip <= lsnif::converter::Gate::kCalibratedMaxFlip);
        CHECK_FALSE(mesh["metrics"]["gate"].contains("above_calibrated_gate"));
    }
}

void check_targets(const nlohmann::json& mesh) {
    print_families(mesh);
    // The default target (converter::Target), and the surface family — the shadow, AO and
    // reflection rays a renderer shoots from the object itself — at 97.5 % on its own
    // (docs/model.md "A 64^3 grid").
    const lsnif::converter::Target target;
    const auto& p = mesh["metrics"]["families"]["pooled"];
    // Visibility within two standard errors of the target: the held-out figure is an
    // estimate from ~40,000 rays (about 0.06 points at 98.5 %). The armadillo sits at the
    // target (98.54-98.55 % over seeds 1-6, docs/model.md "The normal loss"), so a strict
    // comparison on one seed would test the draw, not the model.
    const double se = pooled_visibility_standard_error(mesh);
    MESSAGE("pooled visibility " << 100 * p["visibility_accuracy"].get<double>() << " % +- " << 100 * se
                                 << " (one standard error)");
    CHECK(p["visibility_accuracy"].get<double>() >= target.visibility - 2 * se);
    CHECK(p["distance_error_median_pct"].get<double>() <= target.distance_pct);
    CHECK(p["normal_error_median_deg"].get<double>() <= target.normal_deg);
    CHECK(mesh["metrics"]["families"]["surface"]["visibility_accuracy"].get<double>() >= 0.975);
    // The geometric normal is reported, not gated: it is the faceted orientation the
    // network never trains on.
    CHECK(p["geometric_normal_error_median_deg"].get<double>() > 0.0);
    CHECK(mesh["class"] == "complex");
    // The shipped asset's own verdict (not only the best candidate's): met, or short of the
    // target by its visibility alone, within the resolution checked above.
    CHECK((mesh["target"]["met"] == true || p["visibility_accuracy"].get<double>() < target.visibility));
    REQUIRE(mesh.contains("lsnif"));
    MESSAGE("shipped " << mesh["lsnif"]["bytes"] << " bytes for a " << mesh["memory"]["before"]
                       << "-byte BVH; " << mesh["reasons"].back());
    // Never given up: trained to the end, or stopped once the validation curve met the target.
    if (mesh.contains("stopped_early"))
        CHECK(mesh["validation"].back()["step"] == mesh["stopped_early"]["step"]);
    else
        CHECK(mesh["validation"].size() == 10);
}

// The sizing search as the manifest records it (docs/model.md "Sizing to the target"): the
// first rung is the preset's first size (or triage's, when smaller); a larger rung was
// trained exactly when that rung ran to its end, missed the target and was near it on the
// decision rays (near_target); nothing larger than triage's size. Returns the table size
// shipped (0 when none).
std::uint32_t check_search(const nlohmann::json& mesh) {
    lsnif::converter::Preset preset;
    REQUIRE(lsnif::converter::find_preset("default", preset));
    const auto& cands = mesh["candidates"];
    REQUIRE_FALSE(cands.empty());
    const std::uint32_t largest = mesh["stats"]["log2_table_size"].get<std::uint32_t>();
    const std::uint32_t first = cands[0]["log2_table_size"].get<std::uint32_t>();
    CHECK(first == std::min(largest, preset.sizing.first_log2_table_size));
    bool first_met = false, climbed = false;
    std::uint32_t shipped = 0;
    lsnif::samples::FamilyMetrics decided;
    for (const auto& c : cands) {
        const std::uint32_t log2 = c["log2_table_size"].get<std::uint32_t>();
        CHECK(log2 <= largest);
        if (log2 == first) first_met = first_met || c["target_met"].get<bool>();
        if (log2 == first && c["grid"] == "fp16") {
            decided.visibility_accuracy = c["decided"]["visibility"].get<double>();
            decided.distance_median_pct = c["decided"]["distance_pct"].get<double>();
            decided.normal_median_deg = c["decided"]["normal_deg"].get<double>();
            // Ran to its end or met the target: not given up.
            CHECK((!c.contains("stopped") || c["stopped"].get<std::string>().rfind("given up", 0) != 0));
        }
        climbed = climbed || log2 > first;
        if (c["outcome"].get<std::string>().rfind("chosen", 0) == 0) shipped = log2;
    }
    const lsnif::converter::Target aim;
    const bool near = lsnif::converter::near_target(decided, aim, preset.sizing);
    const std::string verdict = std::string(first_met ? " met the target" : " missed it") +
                                (near ? " (near it)" : "") + (climbed ? "; climbed" : "");
    MESSAGE("search: first 2^" << first << verdict << "; shipped 2^" << shipped << " of at most 2^"
                               << largest);
    CHECK(climbed == (!first_met && near && first < largest));
    return shipped;
}

// The shipped asset read back, and held-out rays drawn afresh from its mesh (Embree ground
// truth, a seed the conversion did not use).
struct Shipped {
    lsnif::format::ModelData model;
    std::vector<lsnif::samples::Sample> held;
    std::vector<lsnif::format::Ray> rays;
    std::vector<lsnif::sampling::SampleExtras> extras;  // per held-out sample: side, triangles
    std::vector<std::array<float, 3>> source_normal;    // family (b): the left triangle's normal
};

Shipped read_shipped(const nlohmann::json& mesh, const fs::path& file, const std::string& name) {
    using namespace lsnif;
    const fs::path asset =
        fs::path(LSNIF_TEST_WORK_DIR) / ("accuracy_" + name) / mesh["lsnif"]["file"].get<std::string>();
    std::ifstream in(asset, std::ios::binary);
    const std::vector<std::uint8_t> bytes{std::istreambuf_iterator<char>(in), {}};
    auto model = format::read_model(bytes);
    REQUIRE(model);
    Shipped s{std::move(*model), {}, {}, {}, {}};
    auto imported = scene::import_scene(file.string());
    REQUIRE(imported.ok());
    const mesh::MeshView view = converter::stages::view_of(imported.scene.meshes[0]);
    const auto box = voxelize::padded_box(view);
    REQUIRE(box);
    std::string error;
    auto source = sampling::EmbreeSource::create(view, *box, {}, error);
    REQUIRE_MESSAGE(source, error);
    source->generate(977, 1u << 16, s.held, &s.extras);
    s.source_normal.resize(s.held.size());
    for (std::size_t i = 0; i < s.held.size(); ++i) {
        const std::uint32_t t = s.extras[i].source_primitive;
        if (t == sampling::kNoPrimitive) continue;
        float p[3][3];
        for (int k = 0; k < 3; ++k)
            for (int a = 0; a < 3; ++a) p[k][a] = view.positions[view.indices[3 * t + k] * 3 + a];
        const float e1[3] = {p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]};
        const float e2[3] = {p[2][0] - p[0][0], p[2][1] - p[0][1], p[2][2] - p[0][2]};
        const float n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                            e1[0] * e2[1] - e1[1] * e2[0]};
        const float len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        if (len > 0) s.source_normal[i] = {n[0] / len, n[1] / len, n[2] / len};
    }
    for (const auto& h : s.held) s.rays.push_back(h.ray);
    return s;
}

// The manifest's held-out figures are on rays no decision saw; rays drawn afresh (seed 977)
// are another such sample: the target holds on them too, within the noise of 2^16 rays
// (about 0.1 point of visibility at two standard deviations), and they agree with the
// manifest's figures as two samples of one model do.
void check_fresh_rays(const Shipped& s, const nlohmann::json& mesh, const std::string& name) {
    const lsnif::samples::Metrics m =
        lsnif::samples::held_out_metrics(lsnif::format::make_runtime(s.model), s.held);
    const auto& reported = mesh["metrics"]["families"]["pooled"];
    const lsnif::converter::Target target;
    MESSAGE(name << " on fresh rays (seed 977): visibility " << 100 * m.pooled.visibility_accuracy
                 << " %, distance " << m.pooled.distance_median_pct << " %, normal "
                 << m.pooled.normal_median_deg << " deg, surface " << 100 * m.family[1].visibility_accuracy
                 << " %; the manifest's: " << 100 * reported["visibility_accuracy"].get<double>() << " %");
    CHECK(m.pooled.visibility_accuracy >= target.visibility - 0.002);
    CHECK(m.pooled.distance_median_pct <= target.distance_pct);
    CHECK(m.pooled.normal_median_deg <= target.normal_deg + 0.3);
    CHECK(std::fabs(m.pooled.visibility_accuracy - reported["visibility_accuracy"].get<double>()) <= 0.003);
}

// The 16-lane voxel walk and the 16-point encoder that intersect() uses give the scalar
// walk's entry points and the per-ray encoder's rows bit for bit on the asset's real
// occupancy grid and tables (tests/format/test_walk.cpp and test_forward.cpp cover the edge
// cases).
void check_walks_agree(const Shipped& s, const std::string& name) {
    using namespace lsnif::format;
    const Geometry geo = make_geometry(s.model.desc);
    const OccupancyGrid occ(s.model.desc.grid_resolution, s.model.occupancy);
    std::vector<RayPoints> got(s.rays.size());
    std::vector<TraceStatus> status(s.rays.size());
    trace_points_batch(geo, occ, s.rays, got.data(), status.data());
    std::size_t same = 0, traced = 0;
    RayPoints want;
    for (std::size_t i = 0; i < s.rays.size(); ++i) {
        const TraceStatus st = trace_points(geo, occ, s.rays[i], want);
        bool equal = st == status[i];
        if (st == TraceStatus::ok) {
            ++traced;
            equal = equal && want.count == got[i].count &&
                    std::memcmp(want.t, got[i].t, sizeof(float) * want.count) == 0 &&
                    std::memcmp(want.g, got[i].g, sizeof(float) * 3 * want.count) == 0 &&
                    std::memcmp(want.voxel, got[i].voxel, sizeof(std::uint32_t) * want.count) == 0;
        }
        same += equal;
    }
    MESSAGE(name << ": 16-lane walk "
                 << std::string(cpu_features().avx512 ? "(AVX-512)" : "(scalar fallback)")
                 << " equals the scalar walk on " << same << " of " << s.rays.size() << " held-out rays ("
                 << traced << " reach the network)");
    CHECK(same == s.rays.size());
    CHECK(traced > s.rays.size() / 2);

    // The 16-point encoder that intersect() uses gives the per-ray encoder's MLP inputs bit
    // for bit on the asset's own (8-bit or fp16) tables.
    const Runtime rt = make_runtime(s.model);
    const auto grid = rt.grid_views();
    std::vector<std::uint32_t> which;
    for (std::size_t i = 0; i < s.rays.size(); ++i)
        if (status[i] == TraceStatus::ok) which.push_back(std::uint32_t(i));
    std::vector<float> rows(which.size() * geo.input_width), row(geo.input_width);
    encode_batch(geo, grid.data(), got.data(), which, rows.data());
    std::size_t rows_same = 0;
    for (std::size_t j = 0; j < which.size(); ++j) {
        encode_points(geo, grid.data(), got[which[j]], row.data());
        rows_same +=
            std::memcmp(row.data(), rows.data() + j * geo.input_width, row.size() * sizeof(float)) == 0;
    }
    MESSAGE(name << ": 16-point encoder equals the per-ray encoder on " << rows_same << " of " << which.size()
                 << " rows");
    CHECK(rows_same == which.size());
}

// The escape rule (docs/model.md) on the held-out rays a renderer shoots from a surface:
// front-side visibility and false misses against the mesh for N = 0 (off) .. 3, printed;
// returned in percent.
struct EscapeFigures {
    std::array<double, 4> visibility, false_misses;
};
EscapeFigures report_escape_rule(const Shipped& s, const std::string& name) {
    using namespace lsnif;
    format::Runtime rt = format::make_runtime(s.model);
    std::vector<samples::Sample> front;
    for (std::size_t i = 0; i < s.held.size(); ++i)
        if (s.held[i].family == samples::Family::surface && s.extras[i].side == 1) front.push_back(s.held[i]);
    EscapeFigures f{};
    for (std::uint32_t n = 0; n < f.visibility.size(); ++n) {
        rt.escape_points = n;
        const samples::FamilyMetrics m =
            samples::held_out_metrics(rt, front).family[int(samples::Family::surface)];
        f.visibility[n] = 100 * m.visibility_accuracy;
        f.false_misses[n] = 100 * m.false_miss_rate;
        MESSAGE(name << " front-side surface rays, escape rule N = " << n << ": visibility "
                     << f.visibility[n] << " % (false hits " << 100 * m.false_hit_rate << " %, false misses "
                     << f.false_misses[n] << " %)");
    }
    return f;
}

// The enclosed rule (docs/model.md) on the held-out rays, per family: occlusion answers against
// the mesh's with the rule off and on, both with the escape rule conversion chose (what a
// renderer runs; the enclosed rule comes first). It only turns misses into hits, so it may add false
// hits where voxels of nearby parts shut in space outside the surface; on rays from outside,
// from inside and leaving the surface's front side (a renderer's occlusion rays) it must not
// add more wrong answers than it removes, beyond 0.1 point. Rays leaving the back side start
// inside the surface, which the rule cannot tell: reported, not checked.
void check_enclosed_rule(const Shipped& s, const nlohmann::json& mesh, const std::string& name) {
    using namespace lsnif;
    format::Runtime rt = format::make_runtime(s.model);
    rt.escape_points = mesh["metrics"]["escape_points"].get<std::uint32_t>();
    std::vector<format::Ray> rays;
    for (const samples::Sample& x : s.held) rays.push_back(x.ray);
    std::vector<std::uint8_t> off(rays.size()), on(rays.size());
    format::occluded(rt, rays, off);
    format::set_enclosed_rule(rt, true);
    format::occluded(rt, rays, on);
    for (int f = 0; f < samples::kFamilyCount + 2; ++f) {
        std::size_t n = 0, wrong_off = 0, wrong_on = 0, taken = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) {
            if (f < samples::kFamilyCount ? int(s.held[i].family) != f
                                          : (s.held[i].family != samples::Family::surface ||
                                             s.extras[i].side != (f == samples::kFamilyCount ? 1 : -1)))
                continue;
            ++n;
            wrong_off += off[i] != s.held[i].hit;
            wrong_on += on[i] != s.held[i].hit;
            taken += on[i] != off[i];
        }
        if (!n) continue;
        const double before = 100.0 * double(wrong_off) / double(n),
                     after = 100.0 * double(wrong_on) / double(n);
        const std::string family = f < samples::kFamilyCount
                                       ? std::string(samples::family_name(samples::Family(f)))
                                   : f == samples::kFamilyCount ? "front-side surface"
                                                                : "back-side surface";
        MESSAGE(name << " " << family << " rays, occlusion answers wrong (escape rule at " << rt.escape_points
                     << "): " << before << " % with the enclosed rule off, " << after << " % on (" << taken
                     << " of " << n << " answers turned to hits)");
        const bool checked = f == int(samples::Family::outside) || f == int(samples::Family::interior) ||
                             f == samples::kFamilyCount;
        if (checked) CHECK(after <= before + 0.1);
    }
}

// The limit conversion chose (the decision rays' false misses rise by at most
// kEscapeMissRise) lies in [lowest, highest], and holds on the held-out rays: their false
// misses rise by at most that plus 0.1 point (about two standard deviations of the lost
// occluders' count on ~11,000 rays), and visibility does not drop by more than 0.1 point.
// Which N a solid's model allows moves with its training (2 or 3 on these meshes); that the
// rule is on for a solid and off for thin parts does not.
void check_escape_choice(const nlohmann::json& mesh, const EscapeFigures& f, std::uint32_t lowest,
                         std::uint32_t highest) {
    const std::uint32_t n = mesh["metrics"]["escape_points"].get<std::uint32_t>();
    CHECK(n >= lowest);
    CHECK(n <= highest);
    if (n == 0 || n >= f.visibility.size()) return;
    CHECK(f.visibility[n] >= f.visibility[0] - 0.1);
    CHECK(f.false_misses[n] <= f.false_misses[0] + 100 * lsnif::converter::stages::kEscapeMissRise + 0.1);
}

// The surface family split by the side its rays leave from: the front
// of the geometric normal, where a renderer's shadow, AO and reflection rays start on an
// opaque object, and the back, inside a closed solid. Both halves are measured and must be
// there; the split is printed so that work on surface rays can see which side errs.
void report_surface_sides(const Shipped& s, const std::string& name) {
    using namespace lsnif;
    const format::Runtime rt = format::make_runtime(s.model);
    // The surface family's metrics over the held-out samples i with keep(i).
    const auto surface_metrics = [&](auto&& keep) {
        std::vector<samples::Sample> part;
        for (std::size_t i = 0; i < s.held.size(); ++i)
            if (s.held[i].family == samples::Family::surface && keep(i)) part.push_back(s.held[i]);
        return samples::held_out_metrics(rt, part).family[int(samples::Family::surface)];
    };
    for (const int side : {+1, -1}) {
        const samples::FamilyMetrics m =
            surface_metrics([&](std::size_t i) { return s.extras[i].side == side; });
        const std::string which = side > 0 ? "front" : "back";
        MESSAGE(name << " surface rays leaving the " << which << ": " << m.rays << " rays, visibility "
                     << 100 * m.visibility_accuracy << " % (false hits " << 100 * m.false_hit_rate
                     << " %, false misses " << 100 * m.false_miss_rate << " %), distance "
                     << m.distance_median_pct << " %, normal " << m.normal_median_deg << " deg");
        CHECK(m.rays > s.held.size() / 10);
    }
    // Front-side rays by the cosine of their angle to the geometric normal: grazing rays
    // (near the terminator of a light behind them) against steep ones.
    const double edges[] = {0.0, 0.15, 0.5, 1.01};
    for (int b = 0; b < 3; ++b) {
        const samples::FamilyMetrics m = surface_metrics([&](std::size_t i) {
            if (s.extras[i].side != 1) return false;
            const auto& d = s.held[i].ray.dir;
            const auto& n = s.source_normal[i];
            const double c = std::fabs(d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) /
                             std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            return c >= edges[b] && c < edges[b + 1];
        });
        MESSAGE(name << " front-side rays with cos in [" << edges[b] << ", " << std::min(1.0, edges[b + 1])
                     << "): " << m.rays << " rays, visibility " << 100 * m.visibility_accuracy
                     << " % (false hits " << 100 * m.false_hit_rate << " %, false misses "
                     << 100 * m.false_miss_rate << " %)");
    }
}

// The shipped asset evaluated with reduced-precision hidden layers (format::MlpArithmetic:
// bf16 on CPUs with AVX-512 BF16, int8 on CPUs with AVX-512 VNNI, what lsnif_open picks)
// against the fp32 reference on the held-out rays: hit decisions agree on >= 99.5 % of the
// rays that reach the network, and the pooled metrics move by <= 0.1 point (visibility in
// percent, distance in percent of the diagonal, normal in degrees).
void check_reduced_inference(const Shipped& s, const std::string& name,
                             lsnif::format::MlpArithmetic arithmetic) {
    using namespace lsnif;
    const std::string label = arithmetic == format::MlpArithmetic::int8 ? "int8" : "bf16";
    const format::Runtime fp32 = format::make_runtime(s.model, format::MlpArithmetic::fp32);
    const format::Runtime reduced = format::make_runtime(s.model, arithmetic);
    if (format::mlp_arithmetic(reduced.net) != arithmetic) {
        const std::string isa = arithmetic == format::MlpArithmetic::int8 ? "avx512vnni" : "avx512bf16";
        if (test::runner_expects(isa))
            FAIL_CHECK("this CPU lacks the instructions of "
                       << label << " inference, and LSNIF_TEST_EXPECT lists " << isa);
        else
            MESSAGE("this CPU lacks the instructions of " << label << " inference: not compared");
        return;
    }
    const auto& rays = s.rays;
    std::vector<format::Hit> h32(rays.size()), hr(rays.size());
    const auto s32 = format::intersect(fp32, rays, h32);
    format::intersect(reduced, rays, hr);
    std::size_t agree = 0;
    for (std::size_t i = 0; i < rays.size(); ++i) agree += h32[i].hit == hr[i].hit;
    const std::size_t culled = rays.size() - s32.inferred;  // agree trivially: no inference
    const double agreement = double(agree - culled) / double(s32.inferred);
    const samples::Metrics m32 = samples::held_out_metrics(fp32, s.held),
                           mr = samples::held_out_metrics(reduced, s.held);
    MESSAGE(name << " " << label << " vs fp32: hit agreement " << 100 * agreement << " % of " << s32.inferred
                 << " inferred rays; pooled visibility " << 100 * m32.pooled.visibility_accuracy << " -> "
                 << 100 * mr.pooled.visibility_accuracy << " %, distance " << m32.pooled.distance_median_pct
                 << " -> " << mr.pooled.distance_median_pct << " %, normal " << m32.pooled.normal_median_deg
                 << " -> " << mr.pooled.normal_median_deg << " deg");
    CHECK(agreement >= 0.995);
    CHECK(std::fabs(mr.pooled.visibility_accuracy - m32.pooled.visibility_accuracy) * 100 <= 0.1);
    CHECK(std::fabs(mr.pooled.distance_median_pct - m32.pooled.distance_median_pct) <= 0.1);
    CHECK(std::fabs(mr.pooled.normal_median_deg - m32.pooled.normal_median_deg) <= 0.1);
}

void check_reduced_inference(const Shipped& s, const std::string& name) {
    check_reduced_inference(s, name, lsnif::format::MlpArithmetic::bf16);
    check_reduced_inference(s, name, lsnif::format::MlpArithmetic::int8);
}

}  // namespace

// Held in memory, the 20k-triangle dragon's default model at 2^17 rows (0.67 MB) just halves
// its Embree BVH (1.4 MB), so the memory rule's estimate at triage
// (tests/convert/test_convert.cpp checks it) hangs on a few KB; the model's accuracy is
// measured forced, at the preset's size, whatever the rule decides.
TEST_CASE("the default model meets the accuracy targets on CGAL's Chinese dragon (forced)") {
    const auto mesh = convert_default(cgal_mesh("ChineseDragon-10kv.off"), "ChineseDragon-10kv", true);
    check_targets(mesh);
    // A smaller table than the largest serves it: the search ships it, meeting the target.
    CHECK(check_search(mesh) < mesh["stats"]["log2_table_size"].get<std::uint32_t>());
    CHECK(mesh["target"]["met"] == true);
    check_shipped_asset(mesh, accuracy_dir("ChineseDragon-10kv"));
    const Shipped shipped = read_shipped(mesh, cgal_mesh("ChineseDragon-10kv.off"), "ChineseDragon-10kv");
    check_fresh_rays(shipped, mesh, "ChineseDragon-10kv");
    check_walks_agree(shipped, "ChineseDragon-10kv");
    report_surface_sides(shipped, "ChineseDragon-10kv");
    // On a solid the rule at N = 2 or 3 answers about as well as the network, and conversion
    // chooses it (docs/model.md "The escape rule").
    check_escape_choice(mesh, report_escape_rule(shipped, "ChineseDragon-10kv"), 2, 3);
    check_enclosed_rule(shipped, mesh, "ChineseDragon-10kv");
    check_reduced_inference(shipped, "ChineseDragon-10kv");
}

TEST_CASE("default preset meets the accuracy targets on CGAL's armadillo") {
    const auto mesh = convert_default(cgal_mesh("armadillo.off"), "armadillo");
    check_targets(mesh);
    check_search(mesh);
    check_shipped_asset(mesh, accuracy_dir("armadillo"));
    const Shipped shipped = read_shipped(mesh, cgal_mesh("armadillo.off"), "armadillo");
    check_fresh_rays(shipped, mesh, "armadillo");
    check_walks_agree(shipped, "armadillo");
    report_surface_sides(shipped, "armadillo");
    check_escape_choice(mesh, report_escape_rule(shipped, "armadillo"), 2, 3);
    check_enclosed_rule(shipped, mesh, "armadillo");
    check_reduced_inference(shipped, "armadillo");
}

// A CAD-like assembly (BlendSwap's Peterbilt truck, CC0, 116,495 triangles in hundreds of
// parts: thin panels, wheels, chrome trim) ships, but short of the default target
// (docs/investigations/real-meshes.md): the gate's figures with a margin over them, and the
// shipped asset's walk and bf16 inference checked like the CGAL meshes'.
TEST_CASE("default preset ships a truck assembly past the gate with a margin") {
    const fs::path file = furniture_mesh("blendswap-cc-0/peterbilt");
    const auto mesh = convert_default(file, "peterbilt");
    print_families(mesh);
    REQUIRE(mesh["class"] == "complex");
    REQUIRE(mesh.contains("lsnif"));
    check_shipped_asset(mesh, accuracy_dir("peterbilt"));
    const auto& fam = mesh["metrics"]["families"];
    CHECK(fam["pooled"]["visibility_accuracy"].get<double>() >= 0.955);
    CHECK(fam["pooled"]["distance_error_median_pct"].get<double>() <= 1.0);
    CHECK(fam["pooled"]["normal_error_median_deg"].get<double>() <= 15.0);
    for (const char* f : {"outside", "surface", "interior"})
        CHECK(fam[f]["visibility_accuracy"].get<double>() >= 0.92);
    const Shipped shipped = read_shipped(mesh, file, "peterbilt");
    check_walks_agree(shipped, "peterbilt");
    report_surface_sides(shipped, "peterbilt");
    // Thin parts a voxel or two apart: the rule loses real occluders here, so it stays off.
    check_escape_choice(mesh, report_escape_rule(shipped, "peterbilt"), 0, 0);
    check_enclosed_rule(shipped, mesh, "peterbilt");
    check_reduced_inference(shipped, "peterbilt");
}

// Whether `mesh` stays BVH because neither its rays nor its images reach the gate, and says so:
// decided early or below the gate, with the image error over its pixels named against the
// calibrated gate among its reasons.
void check_stays_bvh_by_images(const nlohmann::json& mesh) {
    CHECK(mesh["class"] == "simple");
    CHECK((mesh["decision"] == "decided_early" || mesh["decision"] == "below_gate"));
    CHECK_FALSE(mesh.contains("lsnif"));
    bool image_reason = false;
    for (const auto& why : mesh["reasons"])
        image_reason = image_reason ||
                       why.get<std::string>().find("over the object's pixels > gate") != std::string::npos;
    CHECK(image_reason);
    REQUIRE(!mesh["candidates"].empty());
    CHECK(mesh["candidates"][0]["flip"]["combined_object"].get<double>() >
          lsnif::converter::Gate::kCalibratedMaxFlip);
}

// Foliage (Scopia's Japanese maple, CC-BY 3.0, 198,396 triangles of leaves) is thin geometry
// whose rays the network cannot reach the target on at 64^3 (78 % visibility at the first
// check that may judge): trained again at 128^3, its rays stay far below the gate and its
// image error over its own pixels (0.22) is three times the calibrated image gate, so it
// stays BVH and the manifest says why (docs/model.md "Thin geometry").
TEST_CASE("default preset keeps a tree as BVH, by its rays and its images, after a finer grid") {
    const auto mesh = convert_default(furniture_mesh("scopia/japaneseMaple"), "japaneseMaple");
    print_families(mesh);
    MESSAGE("japaneseMaple: " << mesh["reasons"].dump());
    check_stays_bvh_by_images(mesh);
    CHECK(mesh["candidates"][0]["grid_resolution"] == 128);
}

// The paper-like evaluation scene (docs/eval.md "Scenes like the paper's"): three instances
// of the dragon Loop-subdivided three times (1,279,616 triangles) on a floor, converted with
// the default preset and rendered by `lsnif eval` from the composition's camera, which frames
// the three dragons. The combined image (direct light with shadows, AO and a mirror coat)
// must stay within FLIP 0.03 of the Embree reference over the frame.
TEST_CASE("dragons composition: the combined image is within FLIP 0.03 of the reference") {
    const std::string cgal_data = fs::path(LSNIF_TEST_MESH_DIR).parent_path().parent_path().string();
    const fs::path dir = fs::path(LSNIF_TEST_WORK_DIR) / "accuracy_dragons";
    const ConvertResult r = convert_generated(dir, "--composition dragons --cgal-data " + cgal_data, {});
    REQUIRE(r.ok());
    REQUIRE(r.manifest["meshes"].size() == 2);
    for (const auto& mesh : r.manifest["meshes"])
        if (mesh["name"] == "dragon") {
            CHECK(mesh["class"] == "complex");
            CHECK(mesh["triangles"] == 1279616);
            print_families(mesh);
        }

    lsnif::eval::EvalOptions e;
    e.outdir = (dir / "out").string();
    e.camera = lsnif::render::Camera{{0.45f, 1.0f, 2.7f}, {0.0f, 0.4f, -0.1f}, {0.0f, 1.0f, 0.0f}, 40.0f};
    e.images_dir = (dir / "eval").string();
    const lsnif::eval::EvalResult ev = lsnif::eval::render_and_compare(e);
    REQUIRE_MESSAGE(ev.ok(), (ev.errors.empty() ? "" : ev.errors[0]));
    const lsnif::eval::EvalReport& rep = *ev.report;
    using lsnif::render::kCombined;
    for (int e = 0; e < lsnif::render::kEffects; ++e) {
        const auto& im = rep.hybrid.effect[e];
        MESSAGE("dragons " << lsnif::render::kEffectNames[e] << ": FLIP mean " << im.flip.mean
                           << " over the frame, " << (im.flip_lsnif_pixels ? im.flip_lsnif_pixels->mean : 0.0)
                           << " over the LSNIF pixels");
    }
    MESSAGE("dragons: " << rep.lsnif_pixels << " LSNIF pixels; secondary-ray time hybrid/reference "
                        << rep.secondary_time_ratio());
    CHECK(rep.lsnif_instances == 3);
    // The dragons fill the frame: over a quarter of its pixels are LSNIF hits.
    CHECK(double(rep.lsnif_pixels) > 0.25 * e.width * e.height);
    CHECK(rep.hybrid.effect[kCombined].flip.mean <= 0.03);
    // All-neural: the primary rays through the assets too. Silhouettes and shading normals are
    // the network's, so its error is larger (0.041 over the frame, 0.12 over the LSNIF pixels,
    // docs/eval_scenes.md); the assets cover about the pixels the meshes do.
    const auto& neural = rep.neural.effect[kCombined];
    const auto& hybrid = rep.hybrid.effect[kCombined];
    REQUIRE(neural.flip_lsnif_pixels);
    REQUIRE(hybrid.flip_lsnif_pixels);
    MESSAGE("dragons all-neural: combined FLIP "
            << neural.flip.mean << " over the frame, " << neural.flip_lsnif_pixels->mean << " over "
            << rep.neural_lsnif_pixels << " LSNIF pixels; time all-neural/reference "
            << rep.neural_time_ratio());
    CHECK(neural.flip.mean <= 0.05);
    CHECK(neural.flip_lsnif_pixels->mean > hybrid.flip_lsnif_pixels->mean);
    CHECK(rep.neural_lsnif_pixels >= rep.lsnif_pixels);
    CHECK(rep.neural_time_ratio() > 0.0);
    for (const auto& mesh : r.manifest["meshes"])
        if (mesh.contains("lsnif")) check_shipped_asset(mesh, dir / "out");
}

// Thin geometry under the calibrated image gate (docs/model.md "Thin geometry"): the bundled
// example scene as a user converts it, default options, nothing forced. Its hairball (74,400
// triangles, three instances) cannot reach the target's rays on the 64^3 grid and is trained
// again at 128^3; its image error over its own pixels stays several times the calibrated gate
// (0.27 at the first check that may judge, 0.18 after the whole budget), so it stays BVH with
// that reason; nothing of the scene ships above the gate. The dragon ships by both rules,
// its memory and held-out image error as the manifest records them.
TEST_CASE("the bundled scene keeps its hairball as BVH under the calibrated image gate") {
    const fs::path dir = fs::path(LSNIF_TEST_WORK_DIR) / "accuracy_scene";
    const std::string cgal_data = fs::path(LSNIF_TEST_MESH_DIR).parent_path().parent_path().string();
    const ConvertResult r = convert_generated(dir, "--cgal-data " + cgal_data, {});
    REQUIRE(r.ok());
    bool hairball = false, dragon = false;
    for (const auto& mesh : r.manifest["meshes"]) {
        if (mesh.contains("lsnif")) check_shipped_asset(mesh, dir / "out");
        if (mesh["name"] != "hairball" && mesh["name"] != "dragon") continue;
        print_families(mesh);
        MESSAGE(mesh["name"].get<std::string>() << ": " << mesh["reasons"].dump());
        if (mesh["name"] == "hairball") {
            hairball = true;
            check_stays_bvh_by_images(mesh);
            CHECK(mesh["candidates"][0]["grid_resolution"] == 128);
            bool refined = false;
            for (const auto& why : mesh["reasons"])
                refined =
                    refined || why.get<std::string>().find("trained again at 128^3") != std::string::npos;
            CHECK(refined);
        } else {
            dragon = true;
            REQUIRE(mesh["class"] == "complex");
            CHECK(mesh["metrics"]["gate"]["by"] == "both");
            CHECK(mesh["held_out_images"]["combined_object"].get<double>() <=
                  lsnif::converter::Gate::kCalibratedMaxFlip);
        }
    }
    CHECK(hairball);
    CHECK(dragon);
}
