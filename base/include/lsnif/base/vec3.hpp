// The toolchain's one small double-precision 3-vector, for geometry construction (ray
// sampling in converter/sampling, the procedural meshes of examples/scene) and for hits that
// must be the same on every CPU (triangle_hit.hpp). Header-only,
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

}  // namespace lsnif::base
