// Held-out metrics; see held_out.hpp for the contract. Three stages: the reader answers
// every ray, each answer is tallied into its family, the tallies become metrics.
#include <lsnif/samples/held_out.hpp>

#include <lsnif/base/math.hpp>
#include <lsnif/base/parallel.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace lsnif::samples {

namespace {

// The reader's answer for every sample, and whether occupancy culled the ray (the reader
// then reports a miss without running the network).
struct Predictions {
    std::vector<format::Hit> hits;
    std::vector<std::uint8_t> culled;
};

Predictions predict(const format::Runtime& rt, std::span<const Sample> samples, std::uint32_t threads) {
    const std::uint32_t T = base::resolve_threads(threads);
    std::vector<format::Ray> rays(samples.size());
    for (std::size_t i = 0; i < samples.size(); ++i) rays[i] = samples[i].ray;
    Predictions p{std::vector<format::Hit>(samples.size()), std::vector<std::uint8_t>(samples.size())};
    const std::size_t per = (samples.size() + T - 1) / T;
    base::run_on_threads(T, [&](std::uint32_t t) {
        const std::size_t b = std::min(samples.size(), t * per), e = std::min(samples.size(), b + per);
        if (b >= e) return;
        format::intersect(rt, std::span(rays).subspan(b, e - b), std::span(p.hits).subspan(b, e - b));
        format::RayPoints pts;
        for (std::size_t i = b; i < e; ++i)
            p.culled[i] = format::trace_points(rt.geo, rt.occupancy, rays[i], pts) != format::TraceStatus::ok;
    });
    return p;
}

// Counts and error distributions of one family, in sample order.
struct Tally {
    std::uint64_t rays = 0, culled = 0, correct = 0, true_miss = 0, false_hit = 0, true_hit = 0,
                  false_miss = 0, culled_true_hits = 0;
    std::vector<double> dist, ang, geo_ang;  // % of the diagonal; degrees; degrees
};

double degrees_between(double cosine) {
    return base::acos(std::clamp(cosine, -1.0, 1.0)) * 180.0 / M_PI;
}

void tally_hit_errors(const Sample& s, const format::Hit& h, double diagonal, const std::array<float, 3>* gn,
                      Tally& a) {
    const float dlen =
        std::sqrt(s.ray.dir[0] * s.ray.dir[0] + s.ray.dir[1] * s.ray.dir[1] + s.ray.dir[2] * s.ray.dir[2]);
    a.dist.push_back(100.0 * std::fabs(double(h.t) - s.t) * dlen / diagonal);
    a.ang.push_back(
        degrees_between(h.normal[0] * s.normal[0] + h.normal[1] * s.normal[1] + h.normal[2] * s.normal[2]));
    if (!gn) return;
    // The faceted normal's orientation is the triangle winding's; compare as an unoriented
    // line against it when the shading normal disagrees.
    double cg = h.normal[0] * (*gn)[0] + h.normal[1] * (*gn)[1] + h.normal[2] * (*gn)[2];
    const double sg = s.normal[0] * (*gn)[0] + s.normal[1] * (*gn)[1] + s.normal[2] * (*gn)[2];
    if (sg < 0) cg = -cg;
    a.geo_ang.push_back(degrees_between(cg));
}

void tally(std::span<const Sample> samples, const Predictions& p, double diagonal,
           std::span<const std::array<float, 3>> geometric_normals, Tally (&acc)[kFamilyCount]) {
    for (std::size_t i = 0; i < samples.size(); ++i) {
        const Sample& s = samples[i];
        Tally& a = acc[int(s.family) % kFamilyCount];
        if (p.culled[i]) {
            ++a.culled;
            a.culled_true_hits += s.hit != 0;
            continue;
        }
        ++a.rays;
        const bool pred = p.hits[i].hit != 0;
        a.correct += pred == (s.hit != 0);
        if (!s.hit) {
            ++a.true_miss;
            a.false_hit += pred;
            continue;
        }
        ++a.true_hit;
        a.false_miss += !pred;
        if (pred)
            tally_hit_errors(s, p.hits[i], diagonal,
                             i < geometric_normals.size() ? &geometric_normals[i] : nullptr, a);
    }
}

// Nearest-rank percentile (q in [0, 1]); reorders v. 0 for an empty set.
double percentile(std::vector<double>& v, double q) {
    if (v.empty()) return 0.0;
    const std::size_t k = std::min(v.size() - 1, std::size_t(q * double(v.size() - 1) + 0.5));
    std::nth_element(v.begin(), v.begin() + k, v.end());
    return v[k];
}

// Per-family metrics, and the pooled ones with the three families in equal shares: rates
// are averaged over the families present, distributions take the first min-size entries
// of each family.
Metrics summarize(Tally (&acc)[kFamilyCount]) {
    Metrics m;
    std::vector<double> pooled_dist, pooled_ang, pooled_geo;
    std::size_t min_d = SIZE_MAX, min_a = SIZE_MAX;
    int present = 0;
    for (int f = 0; f < kFamilyCount; ++f)
        if (acc[f].rays) {
            min_d = std::min(min_d, acc[f].dist.size());
            min_a = std::min(min_a, acc[f].ang.size());
        }
    for (int f = 0; f < kFamilyCount; ++f) {
        Tally& a = acc[f];
        FamilyMetrics& fm = m.family[f];
        fm.rays = a.rays;
        fm.culled = a.culled;
        fm.culled_true_hits = a.culled_true_hits;
        fm.culled_fraction = (a.rays + a.culled) ? double(a.culled) / double(a.rays + a.culled) : 0.0;
        if (!a.rays) continue;
        ++present;
        fm.visibility_accuracy = double(a.correct) / double(a.rays);
        fm.false_hit_rate = a.true_miss ? double(a.false_hit) / double(a.true_miss) : 0.0;
        fm.false_miss_rate = a.true_hit ? double(a.false_miss) / double(a.true_hit) : 0.0;
        pooled_dist.insert(pooled_dist.end(), a.dist.begin(), a.dist.begin() + std::ptrdiff_t(min_d));
        pooled_ang.insert(pooled_ang.end(), a.ang.begin(), a.ang.begin() + std::ptrdiff_t(min_a));
        pooled_geo.insert(pooled_geo.end(), a.geo_ang.begin(),
                          a.geo_ang.begin() + std::ptrdiff_t(std::min(min_a, a.geo_ang.size())));
        fm.distance_median_pct = percentile(a.dist, 0.5);
        fm.distance_p95_pct = percentile(a.dist, 0.95);
        fm.normal_median_deg = percentile(a.ang, 0.5);
        fm.normal_p95_deg = percentile(a.ang, 0.95);
        fm.geometric_normal_median_deg = percentile(a.geo_ang, 0.5);
        m.pooled.rays += a.rays;
        m.pooled.culled += a.culled;
        m.pooled.culled_true_hits += a.culled_true_hits;
        m.pooled.visibility_accuracy += fm.visibility_accuracy;
        m.pooled.false_hit_rate += fm.false_hit_rate;
        m.pooled.false_miss_rate += fm.false_miss_rate;
        m.pooled.culled_fraction += fm.culled_fraction;
    }
    if (present) {
        m.pooled.visibility_accuracy /= present;
        m.pooled.false_hit_rate /= present;
        m.pooled.false_miss_rate /= present;
        m.pooled.culled_fraction /= present;
    }
    m.pooled.distance_median_pct = percentile(pooled_dist, 0.5);
    m.pooled.distance_p95_pct = percentile(pooled_dist, 0.95);
    m.pooled.normal_median_deg = percentile(pooled_ang, 0.5);
    m.pooled.normal_p95_deg = percentile(pooled_ang, 0.95);
    m.pooled.geometric_normal_median_deg = percentile(pooled_geo, 0.5);
    return m;
}

}  // namespace

Metrics held_out_metrics(const format::Runtime& rt, std::span<const Sample> samples, std::uint32_t threads,
                         std::span<const std::array<float, 3>> geometric_normals) {
    const Predictions p = predict(rt, samples, threads);
    Tally acc[kFamilyCount];
    tally(samples, p, rt.geo.diagonal, geometric_normals, acc);
    return summarize(acc);
}

}  // namespace lsnif::samples
