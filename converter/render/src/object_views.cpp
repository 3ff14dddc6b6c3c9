// The visual acceptance test of one object: its views on a floor, rendered by Embree once and
// through each candidate asset, compared with FLIP (object_views.hpp).
#include <lsnif/base/math.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/image/flip.hpp>
#include <lsnif/image/image.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/render/render.hpp>
#include "scene_impl.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <optional>

namespace lsnif::render {

namespace {

// A square floor under the object's box, three times its larger horizontal extent across,
// slightly below its lowest point (+Y up, as glTF): it catches the object's shadow and
// contact occlusion and is traced by Embree in both renders.
EvalScene::Impl::Mesh floor_under(const std::array<float, 6>& box) {
    const float cx = 0.5f * (box[0] + box[3]), cz = 0.5f * (box[2] + box[5]);
    const float half = 1.5f * std::max({box[3] - box[0], box[5] - box[2], 1e-30f});
    const float y = box[1] - 1e-3f * std::max({box[3] - box[0], box[4] - box[1], box[5] - box[2]});
    EvalScene::Impl::Mesh m;
    m.name = "floor";
    m.positions = {cx - half, y, cz - half, cx + half, y, cz - half,
                   cx + half, y, cz + half, cx - half, y, cz + half};
    m.normals = {0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0};
    m.indices = {0, 2, 1, 0, 3, 2};
    m.box = {cx - half, y, cz - half, cx + half, y, cz + half};
    return m;
}

// View k of n, drawn from `seed`: the camera at an azimuth within the k-th of n equal
// sectors around +Y and 15 to 55 degrees above the horizon, framing the box's bounding
// sphere in a 40-degree field of view; the light 4 radii away, 30 to 120 degrees to either
// side of the camera and 35 to 75 degrees up; the AO directions from their own seed. The
// angles use base::sin and base::cos, so the views are the same on every machine.
RenderOptions view_options(const std::array<float, 6>& box, std::uint32_t k, std::uint32_t n,
                           const ObjectViewOptions& o) {
    base::SplitMix64 rng{base::mix64(o.seed * base::kGoldenGamma + k)};
    const double deg = base::detail::kPi / 180.0;
    const double azimuth = (360.0 * (double(k) + rng.u01()) / double(std::max(1u, n))) * deg;
    const double elevation = (15.0 + 40.0 * rng.u01()) * deg;
    const double side = (30.0 + 90.0 * rng.u01()) * (rng.next() & 1 ? 1.0 : -1.0) * deg;
    const double light_elevation = (35.0 + 40.0 * rng.u01()) * deg;
    const std::uint64_t ao_seed = rng.next();
    const Vec3 lo{box[0], box[1], box[2]}, hi{box[3], box[4], box[5]};
    const Vec3 center = (lo + hi) * 0.5f;
    const float radius = std::max(0.5f * length(hi - lo), 1e-30f);
    const float fov = 40.0f;
    const auto direction = [](double az, double el) {
        return Vec3{float(base::cos(el) * base::sin(az)), float(base::sin(el)),
                    float(base::cos(el) * base::cos(az))};
    };
    RenderOptions opt;
    opt.width = o.width;
    opt.height = o.height;
    opt.ao_samples = o.ao_samples;
    opt.seed = ao_seed;
    opt.timing_repeats = 1;
    Camera cam;
    cam.target = center;
    cam.eye = center + direction(azimuth, elevation) * float(1.05 * radius / base::sin(0.5 * fov * deg));
    cam.fov_deg = fov;
    opt.camera = cam;
    opt.light = center + direction(azimuth + side, light_elevation) * (4.0f * radius);
    return opt;
}

// View k's combined images (linear RGB) as sRGB PNGs in `dir`, with their FLIP heat map.
bool write_view(const std::vector<float>& reference, const std::vector<float>& hybrid, const View& v,
                const std::string& dir, std::size_t k, std::string& error) {
    image::Image ref{v.W, v.H, reference}, hyb{v.W, v.H, hybrid};
    for (auto* img : {&ref, &hyb})
        for (float& x : img->rgb) x = image::linear_to_srgb(std::clamp(x, 0.0f, 1.0f));
    auto f = image::flip(ref, hyb, image::FlipOptions{});
    if (!f) return error = "flip: " + f.error().message, false;
    const std::string stem = dir + "/view" + std::to_string(k) + "_";
    const image::Image heat = image::heatmap(f->error_map, v.W, v.H);
    const std::pair<std::string, const image::Image*> files[] = {
        {stem + "reference.png", &ref}, {stem + "hybrid.png", &hyb}, {stem + "flip.png", &heat}};
    for (const auto& [file, img] : files)
        if (auto w = image::write_png(file, *img); !w) return error = w.error().message, false;
    return true;
}

}  // namespace

// One view: its settings, primary visibility, the object's pixels and the reference images;
// `through_asset`: the candidate's primary rays are traced through its asset too.
struct ObjectView {
    RenderOptions opt;
    View view;
    GBuffer gb;
    std::vector<std::uint8_t> object_pixels;
    EffectImages reference;
    bool through_asset = false;
};

struct ObjectViews::State {
    std::unique_ptr<EvalScene> scene;
    std::vector<ObjectView> views;
    std::uint32_t threads = 1;
};

ObjectViews::ObjectViews(std::unique_ptr<State> state) : state_(std::move(state)) {}
ObjectViews::~ObjectViews() = default;

std::unique_ptr<ObjectViews> ObjectViews::create(std::span<const float> positions,
                                                 std::span<const std::uint32_t> indices,
                                                 std::span<const float> normals, const ObjectViewOptions& o,
                                                 std::string& error) {
    if (positions.empty() || indices.empty() || normals.size() != positions.size() || o.width == 0 ||
        o.height == 0 || o.views == 0) {
        error = "object views: an empty mesh, normals that do not match the vertices, or no pixels";
        return nullptr;
    }
    // The same images on every x86-64-v3 CPU and for any thread count, since they decide what
    // ships: Embree's AVX2 kernels and one BVH build thread, as the conversion's ground truth
    // (sampling::SamplingConfig::embree_isa), Embree's hits with t, u and v of lsnif's own and
    // ties between triangles decided by lsnif (Impl::exact_hit), and the asset traced in fp32
    // (compare()).
    if (!format::detected_cpu_features().avx2_fma) {
        error = "object views: this CPU has no AVX2 and FMA (x86-64-v3 is the floor)";
        return nullptr;
    }
    auto impl = std::make_unique<EvalScene::Impl>();
    EvalScene::Impl& im = *impl;
    const std::string config = "threads=1,isa=" + o.embree_isa;
    if (!im.open_device(error, config.c_str())) return nullptr;
    im.exact_hits = true;  // before upload(): the meshes then keep their neighbourhoods
    EvalScene::Impl::Mesh object;
    object.name = "object";
    object.positions.assign(positions.begin(), positions.end());
    object.normals.assign(normals.begin(), normals.end());
    object.indices.assign(indices.begin(), indices.end());
    object.box = bounds_of(positions);
    const std::array<float, 6> box = object.box;
    if (!im.upload(std::move(object), error) || !im.upload(floor_under(box), error)) return nullptr;
    // The object's instance is traced through the asset compare() opens; the floor by Embree.
    const Affine identity{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
    if (!im.place(0, identity, true, error) || !im.place(1, identity, false, error) || !im.commit(error))
        return nullptr;
    auto state = std::make_unique<State>();
    state->threads = base::resolve_threads(o.threads);
    state->scene = std::unique_ptr<EvalScene>(new EvalScene(std::move(impl)));
    for (std::uint32_t k = 0; k < o.views; ++k) {
        ObjectView& v = state->views.emplace_back();
        v.opt = view_options(box, k, o.views, o);
        v.view = make_view(v.opt, box);
        v.through_asset = k + 1 == o.views;
        v.gb = render_primary(*state->scene, v.view, state->threads);
        v.object_pixels = lsnif_pixel_mask(v.gb, *state->scene);
        v.reference =
            render_secondary(*state->scene, v.gb, v.view, v.opt, {}, state->threads, Tracers::reference)
                .reference;
    }
    return std::unique_ptr<ObjectViews>(new ObjectViews(std::move(state)));
}

std::uint32_t ObjectViews::view_count() const {
    return std::uint32_t(state_->views.size());
}

base::Result<ObjectFlip, std::string> ObjectViews::compare(std::span<const std::uint8_t> asset) const {
    return compare(asset, {});
}

base::Result<ObjectFlip, std::string> ObjectViews::compare(std::span<const std::uint8_t> asset,
                                                           const std::string& dir) const {
    if (!dir.empty()) {
        std::error_code ec;
        std::filesystem::create_directories(dir, ec);
        if (ec) return dir + ": cannot create directory: " + ec.message();
    }
    EvalScene::Impl& im = *state_->scene->impl_;
    lsnif_error err{};
    lsnif_model* model = nullptr;
    if (lsnif_open_memory(asset.data(), asset.size(), &model, &err) != LSNIF_OK)
        return std::string("object views: the asset does not open: ") + lsnif_status_string(err.status) +
               " (" + err.message + ")";
    im.meshes[0].model = model;  // closed by ~Impl, or below when replaced
    if (lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, nullptr) != LSNIF_OK) {
        lsnif_close(model);
        im.meshes[0].model = nullptr;
        return std::string("object views: the asset cannot be traced in fp32");
    }
    ObjectFlip sum;
    std::vector<float> object_errors;  // the combined image's, over every view's object pixels
    std::string error;
    for (std::size_t k = 0; k < state_->views.size(); ++k) {
        const ObjectView& v = state_->views[k];
        std::optional<GBuffer> own;  // the view traced all through the asset
        if (v.through_asset) own = render_primary(*state_->scene, v.view, state_->threads, true);
        const GBuffer& gb = own ? *own : v.gb;
        const EffectImages hybrid =
            render_secondary(*state_->scene, gb, v.view, v.opt, {}, state_->threads, Tracers::hybrid).hybrid;
        const std::vector<std::uint8_t> mask =
            own ? mask_union(v.object_pixels, lsnif_pixel_mask(*own, *state_->scene)) : v.object_pixels;
        EffectComparison c;
        if (!compare_effect(v.reference, hybrid, v.view, kCombined, mask, {}, false, c, error)) break;
        if (!dir.empty() &&
            !write_view(v.reference.rgb[kCombined], hybrid.rgb[kCombined], v.view, dir, k, error))
            break;
        object_errors.insert(object_errors.end(), c.lsnif_pixel_errors.begin(), c.lsnif_pixel_errors.end());
        sum.combined += c.flip.mean;
    }
    lsnif_close(model);
    im.meshes[0].model = nullptr;
    if (!error.empty()) return error;
    const double n = double(state_->views.size());
    ObjectFlip f{0.0, 0.0, sum.combined / n};
    if (!object_errors.empty()) {
        const image::FlipStats s = image::error_stats(object_errors);
        f.combined_object = s.mean;
        f.combined_object_p95 = s.p95;
    }
    return f;
}

}  // namespace lsnif::render
