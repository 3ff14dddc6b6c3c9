#include <lsnif/analytic/spheres.hpp>

#include <lsnif/base/random.hpp>

#include <algorithm>
#include <cmath>

namespace lsnif::analytic {

using samples::Family;
using samples::Sample;

namespace {

using Rng = base::SplitMix64;

void unit_sphere(Rng& rng, double v[3]) {
    const double z = 2.0 * rng.u01() - 1.0, phi = 2.0 * M_PI * rng.u01();
    const double s = std::sqrt(std::max(0.0, 1.0 - z * z));
    v[0] = s * std::cos(phi);
    v[1] = s * std::sin(phi);
    v[2] = z;
}

// Cosine-weighted direction around unit n (Malley's method on an orthonormal frame).
void cosine_around(Rng& rng, const double n[3], double out[3]) {
    const double r = std::sqrt(rng.u01()), phi = 2.0 * M_PI * rng.u01();
    const double x = r * std::cos(phi), y = r * std::sin(phi), z = std::sqrt(std::max(0.0, 1.0 - r * r));
    // Frisvad-style frame, with the sign trick of Duff et al. 2017.
    const double sign = std::copysign(1.0, n[2]);
    const double a = -1.0 / (sign + n[2]), b = n[0] * n[1] * a;
    const double t[3] = {1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]};
    const double bt[3] = {b, sign + n[1] * n[1] * a, -n[1]};
    for (int i = 0; i < 3; ++i) out[i] = x * t[i] + y * bt[i] + z * n[i];
}

}  // namespace

SpheresSource::SpheresSource(std::vector<Sphere> spheres, std::array<float, 3> box_min,
                             std::array<float, 3> box_max, float shadow_fraction)
    : spheres_(std::move(spheres)), lo_(box_min), hi_(box_max), shadow_fraction_(shadow_fraction) {}

bool SpheresSource::intersect(const format::Ray& ray, float& t_out, float normal[3]) const {
    double best = INFINITY;
    int which = -1;
    for (std::size_t s = 0; s < spheres_.size(); ++s) {
        const Sphere& sp = spheres_[s];
        double oc[3], a = 0, b = 0, c = 0;
        for (int i = 0; i < 3; ++i) {
            oc[i] = double(ray.org[i]) - sp.center[i];
            a += double(ray.dir[i]) * ray.dir[i];
            b += oc[i] * ray.dir[i];
            c += oc[i] * oc[i];
        }
        c -= double(sp.radius) * sp.radius;
        const double disc = b * b - a * c;
        if (disc < 0) continue;
        const double sq = std::sqrt(disc);
        for (double t : {(-b - sq) / a, (-b + sq) / a})
            if (t >= ray.tmin && t <= ray.tmax && t < best) {
                best = t;
                which = int(s);
                break;
            }
    }
    if (which < 0) return false;
    t_out = float(best);
    const Sphere& sp = spheres_[std::size_t(which)];
    for (int i = 0; i < 3; ++i)
        normal[i] = float((ray.org[i] + best * ray.dir[i] - sp.center[i]) / sp.radius);
    const float len = std::sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]);
    for (int i = 0; i < 3; ++i) normal[i] /= len;
    return true;
}

void SpheresSource::generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out) {
    out.resize(count);
    Rng rng{seed * base::kGoldenGamma + 12345};
    double center[3], half[3], diag = 0;
    for (int i = 0; i < 3; ++i) {
        center[i] = 0.5 * (double(lo_[i]) + hi_[i]);
        half[i] = 0.5 * (double(hi_[i]) - lo_[i]);
        diag += 4 * half[i] * half[i];
    }
    diag = std::sqrt(diag);
    auto inside_solid = [&](const double p[3]) {
        for (const Sphere& s : spheres_) {
            double d2 = 0;
            for (int i = 0; i < 3; ++i) d2 += (p[i] - s.center[i]) * (p[i] - s.center[i]);
            if (d2 < double(s.radius) * s.radius) return true;
        }
        return false;
    };
    for (std::size_t k = 0; k < count; ++k) {
        Sample& smp = out[k];
        smp = Sample{};
        smp.family = Family(k % 3);
        double o[3], d[3];
        if (smp.family == Family::outside) {  // (a) from outside the box toward it
            double u[3];
            unit_sphere(rng, u);
            for (int i = 0; i < 3; ++i) o[i] = center[i] + u[i] * 0.75 * diag;
            for (int i = 0; i < 3; ++i) d[i] = center[i] + (2 * rng.u01() - 1) * half[i] - o[i];
        } else if (smp.family == Family::surface) {  // (b) leaving a surface, both sides
            const Sphere& s = spheres_[rng.next() % spheres_.size()];
            double n[3];
            unit_sphere(rng, n);
            const double side = (rng.next() & 1) ? 1.0 : -1.0;
            for (int i = 0; i < 3; ++i) {
                n[i] *= side;
                o[i] = s.center[i] + side * n[i] * s.radius + n[i] * 1e-4 * diag;
            }
            if (rng.next() & 1)
                cosine_around(rng, n, d);
            else {
                unit_sphere(rng, d);
                const double dn = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
                if (dn < 0)
                    for (int i = 0; i < 3; ++i) d[i] -= 2 * dn * n[i];
            }
        } else {  // (c) origins inside the box, outside the solids
            do {
                for (int i = 0; i < 3; ++i) o[i] = center[i] + (2 * rng.u01() - 1) * half[i];
            } while (inside_solid(o));
            unit_sphere(rng, d);
        }
        double len = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        for (int i = 0; i < 3; ++i) {
            smp.ray.org[i] = float(o[i]);
            smp.ray.dir[i] = float(d[i] / len);
        }
        smp.ray.tmin = 0.0f;
        smp.ray.tmax = rng.u01() < shadow_fraction_ ? float(rng.u01() * diag) : INFINITY;
        smp.hit = intersect(smp.ray, smp.t, smp.normal) ? 1 : 0;
    }
}

std::vector<std::uint8_t> SpheresSource::occupancy(const format::ModelDesc& desc) const {
    const std::uint32_t V = desc.grid_resolution;
    std::vector<std::uint8_t> bits((desc.voxel_count() + 7) / 8, 0);
    double cell[3];
    for (int a = 0; a < 3; ++a) cell[a] = (double(desc.box_max[a]) - desc.box_min[a]) / V;
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const std::uint32_t c[3] = {x, y, z};
                bool occ = false;
                for (const Sphere& s : spheres_) {
                    double dmin = 0, dmax = 0;
                    for (int a = 0; a < 3; ++a) {
                        const double lo = desc.box_min[a] + c[a] * cell[a], hi = lo + cell[a];
                        const double p = s.center[a];
                        const double dn = p < lo ? lo - p : (p > hi ? p - hi : 0.0);
                        const double df = std::max(std::fabs(p - lo), std::fabs(p - hi));
                        dmin += dn * dn;
                        dmax += df * df;
                    }
                    // Closed voxel meets the sphere surface iff dmin <= r <= dmax; the
                    // slack keeps it conservative under rounding.
                    const double r = s.radius;
                    if (std::sqrt(dmin) <= r * (1 + 1e-6) && std::sqrt(dmax) >= r * (1 - 1e-6)) occ = true;
                }
                if (occ) {
                    const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                    bits[i >> 3] |= std::uint8_t(1u << (i & 7));
                }
            }
    return bits;
}

}  // namespace lsnif::analytic
