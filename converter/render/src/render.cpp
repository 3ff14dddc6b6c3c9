// Images of a scene through both tracers and their comparison (render.hpp has the contract).
#include <lsnif/base/clock.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/image/image.hpp>
#include <lsnif/render/render.hpp>
#include "scene_impl.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>

namespace lsnif::render {

namespace fs = std::filesystem;
using base::seconds_since;

namespace {

// Pleasant, distinct per-mesh albedo: hue by the golden ratio, fixed saturation and value.
Vec3 albedo(std::uint32_t mesh) {
    const float h = std::fmod(0.13f + 0.618034f * float(mesh), 1.0f) * 6.0f, s = 0.45f, v = 0.85f;
    const float c = v * s, x = c * (1.0f - std::fabs(std::fmod(h, 2.0f) - 1.0f)), m = v - c;
    const int k = int(h) % 6;
    const Vec3 rgb = k == 0   ? Vec3{c, x, 0}
                     : k == 1 ? Vec3{x, c, 0}
                     : k == 2 ? Vec3{0, c, x}
                     : k == 3 ? Vec3{0, x, c}
                     : k == 4 ? Vec3{x, 0, c}
                              : Vec3{c, 0, x};
    return rgb + Vec3{m, m, m};
}

Vec3 sky(Vec3 d) {
    const float u = 0.5f * (normalize(d)[1] + 1.0f);
    return Vec3{0.85f, 0.85f, 0.8f} * (1.0f - u) + Vec3{0.45f, 0.6f, 0.9f} * u;
}

const Vec3 kBackground{0.02f, 0.02f, 0.03f};

}  // namespace

View make_view(const RenderOptions& opt, const std::array<float, 6>& world) {
    View v;
    v.W = opt.width;
    v.H = opt.height;
    const Vec3 lo{world[0], world[1], world[2]}, hi{world[3], world[4], world[5]};
    const Vec3 center = (lo + hi) * 0.5f;
    v.diag = std::max(length(hi - lo), 1e-20f);
    if (opt.camera)
        v.cam = *opt.camera;
    else {
        v.cam.target = center;
        v.cam.eye = center + normalize({0.55f, 0.4f, 1.0f}) * (1.15f * v.diag);
    }
    v.light = opt.light ? *opt.light : center + Vec3{0.5f, 1.2f, 0.7f} * v.diag;
    v.fwd = normalize(v.cam.target - v.cam.eye);
    v.right = cross(v.fwd, v.cam.up);
    if (length(v.right) < 1e-6f) v.right = cross(v.fwd, {1.0f, 0.0f, 0.0f});
    v.right = normalize(v.right);
    v.up = cross(v.right, v.fwd);
    v.tan_half = std::tan(0.5f * v.cam.fov_deg * 3.14159265f / 180.0f);
    v.aspect = float(v.W) / float(v.H);
    return v;
}

GBuffer render_primary(const EvalScene& scene, const View& v, std::uint32_t threads, bool through_assets) {
    const std::vector<EvalScene::Impl::Instance>& instances = scene.impl().instances;
    const std::uint32_t W = v.W, H = v.H;
    GBuffer gb;
    gb.p.resize(std::size_t(W) * H);
    gb.n.resize(gb.p.size());
    gb.inst.assign(gb.p.size(), -1);
    gb.eps.resize(gb.p.size());
    std::vector<double> per_thread(threads, 0.0);
    base::parallel_chunks(H, threads, 1, [&](std::uint32_t t, std::size_t y, std::size_t) {
        std::vector<lsnif_ray> rays(W);
        std::vector<TraceHit> hits(W);
        for (std::uint32_t x = 0; x < W; ++x) {
            const float sx = (2.0f * (float(x) + 0.5f) / float(W) - 1.0f) * v.tan_half * v.aspect;
            const float sy = (1.0f - 2.0f * (float(y) + 0.5f) / float(H)) * v.tan_half;
            const Vec3 d = normalize(v.fwd + v.right * sx + v.up * sy);
            rays[x] = {{v.cam.eye[0], v.cam.eye[1], v.cam.eye[2]}, 0.0f, {d[0], d[1], d[2]}, INFINITY};
        }
        const auto t0 = std::chrono::steady_clock::now();
        scene.closest(through_assets, rays, hits);
        per_thread[t] += seconds_since(t0);
        for (std::uint32_t x = 0; x < W; ++x) {
            const std::size_t i = std::size_t(y) * W + x;
            if (hits[x].instance < 0) continue;
            const Vec3 d{rays[x].dir[0], rays[x].dir[1], rays[x].dir[2]};
            gb.p[i] = v.cam.eye + d * hits[x].t;
            Vec3 n = hits[x].normal;
            if (dot(n, d) > 0.0f) n = n * -1.0f;  // shade the side the camera sees
            gb.n[i] = n;
            gb.inst[i] = hits[x].instance;
            // Same offset rule as the training family (b) rays (sampling.hpp): a fraction of
            // the object's diagonal plus a relative term for far-from-origin geometry.
            const auto& b = instances[hits[x].instance].box;
            const float m = std::max({std::fabs(gb.p[i][0]), std::fabs(gb.p[i][1]), std::fabs(gb.p[i][2])});
            gb.eps[i] = 1e-4f * length(Vec3{b[3] - b[0], b[4] - b[1], b[5] - b[2]}) + 1e-5f * m;
        }
    });
    for (double t : per_thread) gb.trace_seconds += t;
    return gb;
}

// The secondary rays of one row: a shadow ray to the light, S cosine-distributed AO rays
// and a mirror reflection per covered pixel, identical for both tracers (per-pixel random
namespace {

// streams).
struct RowRays {
    std::vector<lsnif_ray> shadow, ao, refl;
    std::vector<std::uint32_t> px;  // the covered pixels' x
};

void make_row_rays(const GBuffer& gb, const View& v, const RenderOptions& opt, std::size_t y, std::uint32_t S,
                   RowRays& rr) {
    for (std::uint32_t x = 0; x < v.W; ++x) {
        const std::size_t i = y * v.W + x;
        if (gb.inst[i] < 0) continue;
        rr.px.push_back(x);
        const Vec3 n = gb.n[i], o = gb.p[i] + n * gb.eps[i];
        const Vec3 tl = v.light - o;
        const float dist = length(tl);
        rr.shadow.push_back({{o[0], o[1], o[2]}, 0.0f, {tl[0] / dist, tl[1] / dist, tl[2] / dist}, dist});
        // Cosine-weighted hemisphere about n (Malley's method), per-pixel stream.
        base::SplitMix64 rng{opt.seed * base::kGoldenGamma + i * 0xD1B54A32D192ED03ull};
        const Vec3 a = std::fabs(n[0]) > 0.5f ? Vec3{0, 1, 0} : Vec3{1, 0, 0};
        const Vec3 tx = normalize(cross(a, n)), ty = cross(n, tx);
        for (std::uint32_t k = 0; k < S; ++k) {
            const float r = std::sqrt(rng.uniform01f()), phi = 6.2831853f * rng.uniform01f();
            const float lx = r * std::cos(phi), ly = r * std::sin(phi);
            const Vec3 d = normalize(tx * lx + ty * ly + n * std::sqrt(std::max(0.0f, 1.0f - r * r)));
            rr.ao.push_back({{o[0], o[1], o[2]}, 0.0f, {d[0], d[1], d[2]}, opt.ao_radius * v.diag});
        }
        const Vec3 vd = normalize(gb.p[i] - v.cam.eye);
        const Vec3 rd = vd - n * (2.0f * dot(vd, n));
        rr.refl.push_back({{o[0], o[1], o[2]}, 0.0f, {rd[0], rd[1], rd[2]}, INFINITY});
    }
}

// Shades pixel k of a row from its traced secondary rays: Lambert with shadow, the open
// fraction of AO rays, the mirror bounce (the hit object's Lambert, or the sky), and the
// three combined as one picture: ambient light scaled by the AO fraction plus shadowed
// direct light, under a 20 % mirror coat.
void shade_pixel(const GBuffer& gb, const View& v, const std::vector<EvalScene::Impl::Instance>& instances,
                 const RowRays& rr, std::size_t k, std::size_t i, std::uint32_t S,
                 const std::vector<std::uint8_t>& shadow_occ, const std::vector<std::uint8_t>& ao_occ,
                 const TraceHit& h, EffectImages& out) {
    const Vec3 base = albedo(instances[gb.inst[i]].mesh);
    const Vec3 ldir = normalize(v.light - gb.p[i]);
    const float lambert = std::max(0.0f, dot(gb.n[i], ldir));
    const float direct = lambert * (shadow_occ[k] ? 0.0f : 1.0f);  // shadowed Lambert term
    const Vec3 sh = base * (0.12f + 0.88f * direct);
    std::uint32_t open = 0;
    for (std::uint32_t q = 0; q < S; ++q) open += ao_occ[k * S + q] ? 0u : 1u;
    const float aov = float(open) / float(S);
    Vec3 rc;
    const lsnif_ray& refl = rr.refl[k];
    const Vec3 rd{refl.dir[0], refl.dir[1], refl.dir[2]};
    if (h.instance >= 0) {
        const Vec3 hp = Vec3{refl.org[0], refl.org[1], refl.org[2]} + rd * h.t;
        Vec3 hn = h.normal;
        if (dot(hn, rd) > 0.0f) hn = hn * -1.0f;
        rc = albedo(instances[h.instance].mesh) *
             (0.2f + 0.8f * std::max(0.0f, dot(hn, normalize(v.light - hp))));
    } else {
        rc = sky(rd);
    }
    const Vec3 diffuse = base * (0.25f * aov + 0.75f * direct);
    const Vec3 combined = diffuse * 0.8f + rc * 0.2f;
    const Vec3 px[kEffects] = {sh, Vec3{aov, aov, aov}, mul(rc, Vec3{0.9f, 0.9f, 0.9f}), combined};
    for (int e = 0; e < kEffects; ++e)
        for (int c = 0; c < 3; ++c) out.rgb[e][i * 3 + c] = px[e][c];
}

}  // namespace

std::vector<float> surface_tmins(const EvalScene& scene, float voxels) {
    const EvalScene::Impl& im = scene.impl();
    if (!(voxels > 0)) return {};
    std::vector<float> tmin(im.instances.size(), 0.0f);
    for (const std::uint32_t i : im.lsnif_instances) {
        const EvalScene::Impl::Instance& in = im.instances[i];
        lsnif_info info{};
        if (lsnif_get_info(im.meshes[in.mesh].model, &info) != LSNIF_OK || info.grid_resolution == 0)
            continue;
        float extent = 0;
        for (int a = 0; a < 3; ++a) extent = std::max(extent, info.box_max[a] - info.box_min[a]);
        float scale = 0;
        for (int c = 0; c < 3; ++c)
            scale = std::max(scale, length(Vec3{in.transform[c], in.transform[4 + c], in.transform[8 + c]}));
        tmin[i] = voxels * (extent / float(info.grid_resolution) * scale);
    }
    return tmin;
}

// surface_tmins() on one row's rays: every secondary ray of a pixel whose primary hit is an
namespace {

// LSNIF instance starts that far from the surface.
void start_later(const GBuffer& gb, const std::vector<float>& surface_tmin, std::size_t row0, std::uint32_t S,
                 RowRays& rr) {
    const auto later = [](lsnif_ray& r, float tmin) { r.tmin = std::min(tmin, r.tmax); };
    for (std::size_t k = 0; k < rr.px.size(); ++k) {
        const float tmin = surface_tmin[gb.inst[row0 + rr.px[k]]];
        if (tmin <= 0) continue;
        later(rr.shadow[k], tmin);
        for (std::uint32_t q = 0; q < S; ++q) later(rr.ao[k * S + q], tmin);
        later(rr.refl[k], tmin);
    }
}

// What one tracer answers for a row's rays.
struct RowHits {
    std::vector<std::uint8_t> shadow_occ, ao_occ;
    std::vector<TraceHit> refl_hit;
};

// Traces a row's secondary rays with one tracer into `hits`, and where the time went into
// `profile` (overwritten); returns the seconds it took.
double trace_row(const EvalScene& scene, bool hybrid, const RowRays& rr, RowHits& hits,
                 SecondaryProfile& profile) {
    hits.shadow_occ.resize(rr.shadow.size());
    hits.ao_occ.resize(rr.ao.size());
    hits.refl_hit.resize(rr.refl.size());
    profile = {};
    const auto t0 = std::chrono::steady_clock::now();
    scene.occluded(hybrid, rr.shadow, hits.shadow_occ, &profile[0]);
    scene.occluded(hybrid, rr.ao, hits.ao_occ, &profile[1]);
    scene.closest(hybrid, rr.refl, hits.refl_hit, &profile[2]);
    return seconds_since(t0);
}

}  // namespace

BothImages render_secondary(const EvalScene& scene, const GBuffer& gb, const View& v,
                            const RenderOptions& opt, const std::vector<float>& surface_tmin,
                            std::uint32_t threads, Tracers tracers) {
    const std::vector<EvalScene::Impl::Instance>& instances = scene.impl().instances;
    const std::uint32_t W = v.W, S = std::max(1u, opt.ao_samples);
    BothImages out;
    for (EffectImages* side : {&out.reference, &out.hybrid})
        for (auto& img : side->rgb) img.assign(std::size_t(W) * v.H * 3, 0.0f);
    std::vector<double> per_thread[2] = {std::vector<double>(threads, 0.0),
                                         std::vector<double>(threads, 0.0)};
    std::vector<SecondaryProfile> profiles[2] = {std::vector<SecondaryProfile>(threads),
                                                 std::vector<SecondaryProfile>(threads)};
    const std::uint32_t repeats = std::max(1u, opt.timing_repeats);
    base::parallel_chunks(v.H, threads, 1, [&](std::uint32_t t, std::size_t y, std::size_t) {
        RowRays rays[2];
        make_row_rays(gb, v, opt, y, S, rays[0]);
        rays[1] = rays[0];
        if (!surface_tmin.empty()) start_later(gb, surface_tmin, y * W, S, rays[1]);
        RowHits hits[2];
        double fastest[2] = {INFINITY, INFINITY};
        SecondaryProfile profile, fastest_profile[2];
        const bool traced[2] = {tracers != Tracers::hybrid, tracers != Tracers::reference};
        for (std::uint32_t r = 0; r < repeats; ++r)
            for (const int side : {0, 1}) {
                if (!traced[side]) continue;
                const double s = trace_row(scene, side == 1, rays[side], hits[side], profile);
                if (s < fastest[side]) fastest[side] = s, fastest_profile[side] = profile;
            }
        for (const int side : {0, 1}) {
            if (!traced[side]) continue;
            per_thread[side][t] += fastest[side];
            for (int f = 0; f < kRayFamilies; ++f) profiles[side][t][f] += fastest_profile[side][f];
            const RowRays& rr = rays[side];
            EffectImages& img = side ? out.hybrid : out.reference;
            const auto& [shadow_occ, ao_occ, refl_hit] = hits[side];
            for (std::uint32_t x = 0; x < W; ++x)  // background everywhere first
                for (int e = 0; e < kEffects; ++e)
                    for (int c = 0; c < 3; ++c) img.rgb[e][(y * W + x) * 3 + c] = kBackground[c];
            for (std::size_t k = 0; k < rr.px.size(); ++k)
                shade_pixel(gb, v, instances, rr, k, y * W + rr.px[k], S, shadow_occ, ao_occ, refl_hit[k],
                            img);
        }
    });
    for (double s : per_thread[0]) out.reference.trace_seconds += s;
    for (double s : per_thread[1]) out.hybrid.trace_seconds += s;
    for (std::uint32_t t = 0; t < threads; ++t)
        for (int f = 0; f < kRayFamilies; ++f) {
            out.reference.profile[f] += profiles[0][t][f];
            out.hybrid.profile[f] += profiles[1][t][f];
        }
    return out;
}

namespace {

// The FLIP errors of the pixels `mask` selects, in pixel order.
std::vector<float> masked_errors(const std::vector<float>& error_map, const std::vector<std::uint8_t>& mask) {
    std::vector<float> out;
    for (std::size_t i = 0; i < mask.size(); ++i)
        if (mask[i]) out.push_back(error_map[i]);
    return out;
}

bool write_effect_images(const image::Image& ref, const image::Image& test, const image::FlipResult& f, int e,
                         const std::string& label, const fs::path& images, EffectComparison& c,
                         std::string& error) {
    const std::string stem = kEffectNames[e];
    const std::string flip_stem = label == "hybrid" ? "flip_" : "flip_" + label + "_";
    const image::Image heat = image::heatmap(f.error_map, ref.width, ref.height);
    const std::pair<std::string, const image::Image*> files[] = {{"reference_" + stem + ".png", &ref},
                                                                 {label + "_" + stem + ".png", &test},
                                                                 {flip_stem + stem + ".png", &heat}};
    for (const auto& [file, img] : files) {
        auto w = image::write_png((images / file).string(), *img);
        if (!w) {
            error = w.error().message;
            return false;
        }
    }
    c.files = {files[0].first, files[1].first, files[2].first};
    return true;
}

}  // namespace

bool compare_effect(const EffectImages& reference, const EffectImages& test, const View& v, int e,
                    const std::vector<std::uint8_t>& lsnif_pixels, const fs::path& images, bool write_images,
                    EffectComparison& c, std::string& error, const std::string& label) {
    image::Image ref{v.W, v.H, reference.rgb[e]}, hyb{v.W, v.H, test.rgb[e]};
    for (auto* im2 : {&ref, &hyb})
        for (float& x : im2->rgb) x = image::linear_to_srgb(std::clamp(x, 0.0f, 1.0f));
    auto f = image::flip(ref, hyb, image::FlipOptions{});
    if (!f) {
        error = std::string("flip: ") + kEffectNames[e] + ": " + f.error().message;
        return false;
    }
    c.flip = f->stats;
    c.psnr_db = image::psnr(ref, hyb);
    c.lsnif_pixel_errors = masked_errors(f->error_map, lsnif_pixels);
    if (!c.lsnif_pixel_errors.empty()) c.flip_lsnif_pixels = image::error_stats(c.lsnif_pixel_errors);
    return !write_images || write_effect_images(ref, hyb, *f, e, label, images, c, error);
}

bool compare_effects(const EffectImages& reference, const EffectImages& test, const View& v,
                     const std::vector<std::uint8_t>& lsnif_pixels, const fs::path& images, bool write_images,
                     Comparison& out, std::string& error, const std::string& label) {
    double flip_sum = 0;
    for (int e = 0; e < kEffects; ++e) {
        if (!compare_effect(reference, test, v, e, lsnif_pixels, images, write_images, out.effect[e], error,
                            label))
            return false;
        if (e < kSeparateEffects) flip_sum += out.effect[e].flip.mean;
    }
    out.flip_mean = flip_sum / double(kSeparateEffects);
    return true;
}

// The report's "images": per effect its FLIP, PSNR (null for identical images: infinite),

std::vector<std::uint8_t> mask_union(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b) {
    std::vector<std::uint8_t> out(a.size());
    for (std::size_t i = 0; i < a.size(); ++i) out[i] = a[i] | b[i];
    return out;
}

// 1 for the pixels whose primary hit is an instance the hybrid render traces as an LSNIF.
std::vector<std::uint8_t> lsnif_pixel_mask(const GBuffer& gb, const EvalScene& scene) {
    const EvalScene::Impl& im = scene.impl();
    std::vector<std::uint8_t> traced(im.instances.size(), 0), mask(gb.inst.size(), 0);
    for (const std::uint32_t i : im.lsnif_instances) traced[i] = 1;
    for (std::size_t i = 0; i < gb.inst.size(); ++i) mask[i] = gb.inst[i] >= 0 && traced[gb.inst[i]];
    return mask;
}

}  // namespace lsnif::render
