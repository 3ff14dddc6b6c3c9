// The toolchain's one small double-precision 3-vector, for geometry construction (ray
// sampling in converter/sampling, the procedural meshes of examples/scene) and for hits that
// must be the same on every CPU (triangle_hit). Header-only,
// standard library only. Every operation is a plain expression: callers that promise
// bit-identical output across builds compile with -ffp-contract=off, so the compiler
// cannot fuse a*b+c differently in different places.
#pragma once

#include <cmath>

namespace lsnif::base {

struct Vec3d {
    double x = 0, y = 0, z = 0;
};

inline Vec3d operator+(Vec3d a, Vec3d b) {
    return {a.x + b.x, a.y + b.y, a.z + b.z};
}
inline Vec3d operator-(Vec3d a, Vec3d b) {
    return {a.x - b.x, a.y - b.y, a.z - b.z};
}
inline Vec3d operator*(double s, Vec3d a) {
    return {s * a.x, s * a.y, s * a.z};
}
inline double dot(Vec3d a, Vec3d b) {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}
inline Vec3d cross(Vec3d a, Vec3d b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double length(Vec3d a) {
    return std::sqrt(dot(a, a));
}
// a / |a|; requires |a| > 0.
inline Vec3d normalize(Vec3d a) {
    return (1.0 / length(a)) * a;
}

// Where the ray org + t dir meets the plane of the triangle v0 + u e1 + v e2 (e1 = v1 - v0,
// e2 = v2 - v0): t, and the barycentrics u of v1 and v2 of v2. Möller and Trumbore, "Fast,
// Minimum Storage Ray/Triangle Intersection" (1997), in double, each operation rounded by
// IEEE 754 alone, so every CPU gets the same bits: Embree scales its own t, u and v by an
// approximate reciprocal whose bits are the CPU's (Intel and AMD differ). For a triangle a
// tracer reported; no inside test. False, `out` untouched, when the ray is parallel to the
// triangle in double or a result is not finite.
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

}  // namespace lsnif::base
