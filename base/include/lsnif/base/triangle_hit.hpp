// Ray-triangle hits that are the same on every CPU, for what decides a conversion's bytes:
// the ground truth of the training rays (converter/sampling) and the visual check's images
// (converter/render's object views). Embree says which triangle a ray meets; these compute
// where, in double with IEEE 754's rounding alone (Embree scales its own t, u and v by an
// approximate reciprocal whose bits are the CPU's), and decide between triangles that meet
// the ray at one point (Embree puts first whichever its approximate distances say).
// Header-only, standard library only; callers compile with -ffp-contract=off (vec3.hpp).
#pragma once

#include <lsnif/base/vec3.hpp>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

namespace lsnif::base {

// Where the ray org + t dir meets the plane of the triangle v0 + u e1 + v e2 (e1 = v1 - v0,
// e2 = v2 - v0): t, and the barycentrics u of v1 and v of v2. Möller and Trumbore, "Fast,
// Minimum Storage Ray/Triangle Intersection" (1997). No inside test: for a triangle a tracer
// reported. False, `out` untouched, when the ray is parallel to the triangle in double or a
// result is not finite.
struct TriangleHit {
    double t = 0, u = 0, v = 0;
};
inline bool triangle_hit(Vec3d org, Vec3d dir, Vec3d v0, Vec3d e1, Vec3d e2, TriangleHit& out) {
    const Vec3d from_v0 = org - v0;
    const Vec3d p = cross(dir, e2), q = cross(from_v0, e1);
    const double det = dot(e1, p);
    const double t = dot(e2, q) / det, u = dot(from_v0, p) / det, v = dot(dir, q) / det;
    if (det == 0 || !std::isfinite(t) || !std::isfinite(u) || !std::isfinite(v)) return false;
    out = {t, u, v};
    return true;
}

// How far the point of barycentrics (u of v1, v of v2) lies inside the triangle of edges e1,
// e2, as a distance: the least of each barycentric times the triangle's height over the
// opposite edge (negative outside). NaN for a degenerate triangle (compares false).
inline double inside_distance(Vec3d e1, Vec3d e2, double u, double v) {
    const double area2 = length(cross(e1, e2));
    return std::min(
        {u * area2 / length(e2), v * area2 / length(e1), (1.0 - u - v) * area2 / length(e2 - e1)});
}

// The distance within which a hit counts as on its triangle's border (tied): about a
// millionth of the mesh's extent (its largest absolute coordinate plus its diagonal), a few
// ulps of its coordinates in float, which is what Embree's float edge tests can be off by,
// and far below any triangle a tracer tells apart. A distance, not a barycentric: a small
// triangle and its large neighbour at one point have very different barycentrics there.
inline double tie_margin(const double lo[3], const double hi[3]) {
    const Vec3d d{hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]};
    double largest = 0;
    for (int a = 0; a < 3; ++a) largest = std::max({largest, std::abs(lo[a]), std::abs(hi[a])});
    return 1e-6 * (largest + length(d));
}

// The triangles around each vertex of a triangle list: those of vertex k are
// triangles[first[k] .. first[k + 1]), in index order. `indices` holds 3 per triangle, each
// below vertex_count.
struct VertexTriangles {
    std::vector<std::uint32_t> first, triangles;
    VertexTriangles() = default;
    VertexTriangles(std::span<const std::uint32_t> indices, std::size_t vertex_count)
        : first(vertex_count + 1, 0), triangles(indices.size()) {
        for (const std::uint32_t v : indices) ++first[v + 1];
        for (std::size_t k = 0; k < vertex_count; ++k) first[k + 1] += first[k];
        std::vector<std::uint32_t> fill(first.begin(), first.end() - 1);
        for (std::size_t k = 0; k < indices.size(); ++k) triangles[fill[indices[k]]++] = std::uint32_t(k / 3);
    }
};

// A triangle and the ray's exact hit with it.
struct ChosenHit {
    std::uint32_t triangle = 0;
    TriangleHit hit;
};

// The exact hit (triangle_hit) of the ray with the triangle a tracer reported (`reported`,
// corners `corners`), on the triangle it is on where several meet the ray at one point: a
// ray meets every triangle at an edge or vertex they share at one point, and this decides
// among them the same way whichever of them was reported. When the reported triangle's hit
// lies within `margin` of its border: among the triangles around its corners that the ray
// meets in [tmin, tmax] within `margin` of their own borders, the nearest (t in double), the
// lowest index among equals; otherwise the reported one. The tied triangles share an edge or
// a vertex with each other, so each one's neighbourhood holds the others.
// `triangle(c, v0, e1, e2)` gives triangle c's corner and edges. Empty when triangle_hit has
// no hit with the reported triangle.
template <class Triangle>
std::optional<ChosenHit> exact_tied_hit(Vec3d org, Vec3d dir, double tmin, double tmax, double margin,
                                        std::uint32_t reported, const std::uint32_t (&corners)[3],
                                        const VertexTriangles& around, Triangle&& triangle) {
    Vec3d v0, e1, e2;
    triangle(reported, v0, e1, e2);
    ChosenHit own{reported, {}};
    if (!triangle_hit(org, dir, v0, e1, e2, own.hit)) return std::nullopt;
    if (!(inside_distance(e1, e2, own.hit.u, own.hit.v) < margin)) return own;
    std::optional<ChosenHit> best;
    for (const std::uint32_t corner : corners)
        for (std::uint32_t k = around.first[corner]; k < around.first[corner + 1]; ++k) {
            const std::uint32_t c = around.triangles[k];
            triangle(c, v0, e1, e2);
            TriangleHit x;
            if (!triangle_hit(org, dir, v0, e1, e2, x)) continue;
            if (!(x.t >= tmin && x.t <= tmax && inside_distance(e1, e2, x.u, x.v) >= -margin)) continue;
            if (!best || x.t < best->hit.t || (x.t == best->hit.t && c < best->triangle))
                best = ChosenHit{c, x};
        }
    return best ? best : own;
}

}  // namespace lsnif::base
