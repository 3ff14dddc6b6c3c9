// samples::held_out_metrics against metrics computed here by hand, on a model whose answer
// is known for every ray: all weights zero, so the network outputs its output-layer bias
// whatever the ray (a constant hit or miss, a constant distance value and normal). Ground
// truth comes from the analytic spheres (exact hits and normals).
#include <lsnif/analytic/spheres.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/samples/held_out.hpp>

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <vector>

using namespace lsnif;
using samples::Family;
using samples::kFamilyCount;
using samples::Sample;

namespace {

// The model's constant output row: visibility logit, distance value, normal.
struct Constant {
    float logit, distance;
    float normal[3];
};

struct Fixture {
    format::ModelDesc desc;
    analytic::SpheresSource source{
        {{{-0.3f, 0.1f, 0.0f}, 0.4f}, {{0.45f, -0.2f, 0.1f}, 0.3f}}, {-1.f, -1.f, -1.f}, {1.f, 1.f, 1.f}};
    std::vector<Sample> rays;
    Fixture() {
        desc.log2_table_size = 12;
        desc.hidden_width = {16};
        desc.box_min = {-1.f, -1.f, -1.f};
        desc.box_max = {1.f, 1.f, 1.f};
        source.generate(7, 6000, rays);
    }
    format::Runtime runtime(const Constant& c) const {
        auto model = format::make_empty_model(desc);
        REQUIRE(model.ok());
        model->occupancy = source.occupancy(desc);
        auto& bias = model->biases.back();
        using Out = format::OutputLayout;
        bias[Out::visibility] = format::float_to_half(c.logit);
        bias[Out::distance] = format::float_to_half(c.distance);
        for (int a = 0; a < 3; ++a) bias[Out::normal + a] = format::float_to_half(c.normal[a]);
        return format::make_runtime(*model);
    }
};

// Nearest-rank percentile, the rule held_out.hpp documents.
double percentile(std::vector<double> v, double q) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    return v[std::min(v.size() - 1, std::size_t(q * double(v.size() - 1) + 0.5))];
}

struct Expected {
    std::uint64_t rays = 0, culled = 0, true_hits = 0;
    std::vector<double> dist, ang;
};

// What a constant model must score, family by family, computed from the definitions.
void expect(const format::Runtime& rt, std::span<const Sample> rays, const Constant& c,
            Expected (&e)[kFamilyCount]) {
    const double nl = std::sqrt(double(c.normal[0]) * c.normal[0] + double(c.normal[1]) * c.normal[1] +
                                double(c.normal[2]) * c.normal[2]);
    for (const Sample& s : rays) {
        Expected& f = e[int(s.family)];
        format::RayPoints p;
        if (format::trace_points(rt.geo, rt.occupancy, s.ray, p) != format::TraceStatus::ok) {
            ++f.culled;
            continue;
        }
        ++f.rays;
        if (!s.hit) continue;
        ++f.true_hits;
        if (!(c.logit > 0)) continue;
        const double dlen =
            std::sqrt(double(s.ray.dir[0]) * s.ray.dir[0] + double(s.ray.dir[1]) * s.ray.dir[1] +
                      double(s.ray.dir[2]) * s.ray.dir[2]);
        const double t = std::clamp(double(p.t[0]) + double(c.distance) * rt.geo.diagonal / dlen,
                                    double(p.t_near), double(p.t_far));
        f.dist.push_back(100.0 * std::fabs(t - s.t) * dlen / rt.geo.diagonal);
        const double cosine =
            (c.normal[0] * s.normal[0] + c.normal[1] * s.normal[1] + c.normal[2] * s.normal[2]) / nl;
        f.ang.push_back(std::acos(std::clamp(cosine, -1.0, 1.0)) * 180.0 / M_PI);
    }
}

}  // namespace

TEST_CASE("held-out metrics of a model that always answers 'hit' match the definitions") {
    const Fixture fx;
    const Constant c{1.0f, 0.25f, {0.0f, 0.0f, 1.0f}};
    const format::Runtime rt = fx.runtime(c);
    const samples::Metrics m = samples::held_out_metrics(rt, fx.rays, 2);
    Expected e[kFamilyCount];
    expect(rt, fx.rays, c, e);
    double pooled_vis = 0;
    std::size_t min_d = SIZE_MAX;
    for (int f = 0; f < kFamilyCount; ++f) min_d = std::min(min_d, e[f].dist.size());
    std::vector<double> pooled_dist;
    for (int f = 0; f < kFamilyCount; ++f) {
        CAPTURE(f);
        const samples::FamilyMetrics& fm = m.family[f];
        REQUIRE(e[f].rays > 200);
        REQUIRE(e[f].true_hits > 50);
        CHECK(fm.rays == e[f].rays);
        CHECK(fm.culled == e[f].culled);
        CHECK(fm.culled_true_hits == 0);  // the spheres' occupancy is conservative
        // Every reachable ray is predicted to hit: right exactly on the true hits.
        CHECK(fm.visibility_accuracy == doctest::Approx(double(e[f].true_hits) / double(e[f].rays)));
        CHECK(fm.false_hit_rate == doctest::Approx(e[f].true_hits < e[f].rays ? 1.0 : 0.0));
        CHECK(fm.false_miss_rate == 0.0);
        CHECK(fm.distance_median_pct == doctest::Approx(percentile(e[f].dist, 0.5)).epsilon(1e-5));
        CHECK(fm.distance_p95_pct == doctest::Approx(percentile(e[f].dist, 0.95)).epsilon(1e-5));
        CHECK(fm.normal_median_deg == doctest::Approx(percentile(e[f].ang, 0.5)).epsilon(1e-4));
        CHECK(fm.culled_fraction == doctest::Approx(double(e[f].culled) / double(e[f].culled + e[f].rays)));
        pooled_vis += fm.visibility_accuracy / kFamilyCount;
        pooled_dist.insert(pooled_dist.end(), e[f].dist.begin(), e[f].dist.begin() + std::ptrdiff_t(min_d));
    }
    // Pooled: the three families in equal shares, whatever their sizes.
    CHECK(m.pooled.visibility_accuracy == doctest::Approx(pooled_vis));
    CHECK(m.pooled.distance_median_pct == doctest::Approx(percentile(pooled_dist, 0.5)).epsilon(1e-5));
    CHECK(m.pooled.rays == e[0].rays + e[1].rays + e[2].rays);
}

TEST_CASE("held-out metrics of a model that always answers 'miss': no distance or normal errors to report") {
    const Fixture fx;
    const Constant c{-1.0f, 0.0f, {0.0f, 0.0f, 1.0f}};
    const format::Runtime rt = fx.runtime(c);
    const samples::Metrics m = samples::held_out_metrics(rt, fx.rays, 1);
    Expected e[kFamilyCount];
    expect(rt, fx.rays, c, e);
    for (int f = 0; f < kFamilyCount; ++f) {
        CAPTURE(f);
        const samples::FamilyMetrics& fm = m.family[f];
        CHECK(fm.visibility_accuracy ==
              doctest::Approx(double(e[f].rays - e[f].true_hits) / double(e[f].rays)));
        CHECK(fm.false_hit_rate == 0.0);
        CHECK(fm.false_miss_rate == 1.0);
        CHECK(fm.distance_median_pct == 0.0);
        CHECK(fm.normal_median_deg == 0.0);
    }
}

TEST_CASE("held-out metrics do not depend on the thread count") {
    const Fixture fx;
    const format::Runtime rt = fx.runtime({1.0f, 0.1f, {0.3f, -0.5f, 0.8f}});
    const samples::Metrics a = samples::held_out_metrics(rt, fx.rays, 1);
    for (std::uint32_t threads : {2u, 3u, 7u}) {
        CAPTURE(threads);
        const samples::Metrics b = samples::held_out_metrics(rt, fx.rays, threads);
        for (int f = 0; f <= kFamilyCount; ++f) {
            const samples::FamilyMetrics& x = f < kFamilyCount ? a.family[f] : a.pooled;
            const samples::FamilyMetrics& y = f < kFamilyCount ? b.family[f] : b.pooled;
            CHECK(x.rays == y.rays);
            CHECK(x.visibility_accuracy == y.visibility_accuracy);
            CHECK(x.distance_median_pct == y.distance_median_pct);
            CHECK(x.normal_p95_deg == y.normal_p95_deg);
        }
    }
}

TEST_CASE("geometric normals: compared as unoriented lines, reported beside the shading error") {
    const Fixture fx;
    const format::Runtime rt = fx.runtime({1.0f, 0.25f, {0.0f, 1.0f, 0.0f}});
    // The faceted normal given with its winding reversed (as an inward-wound mesh would):
    // the error against it must equal the error against the shading normal.
    std::vector<std::array<float, 3>> flipped(fx.rays.size());
    for (std::size_t i = 0; i < fx.rays.size(); ++i)
        for (int a = 0; a < 3; ++a) flipped[i][a] = -fx.rays[i].normal[a];
    const samples::Metrics m = samples::held_out_metrics(rt, fx.rays, 2, flipped);
    for (int f = 0; f < kFamilyCount; ++f) {
        CAPTURE(f);
        CHECK(m.family[f].normal_median_deg > 1.0);
        CHECK(m.family[f].geometric_normal_median_deg == doctest::Approx(m.family[f].normal_median_deg));
    }
    // Without geometric normals the field stays 0.
    CHECK(samples::held_out_metrics(rt, fx.rays, 2).pooled.geometric_normal_median_deg == 0.0);
}
