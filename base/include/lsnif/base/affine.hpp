// The toolchain's one affine-transform helper (header-only): instance transforms as the
// manifest and the C API store them, 3x4 row-major [A | b] with x_world = A x_object + b.
//
// One singularity rule for every caller: a transform is usable when all 12 entries are
// finite and |det A| > 1e-12 * (max |a_ij|)^3, i.e. A is far from singular relative to
// its own scale (a uniform scale of 1e-5 is fine; a flattened axis is not).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <optional>

namespace lsnif::base {

struct LinearInverse {
    // A^-1, row-major. Points map back as A^-1 (x - b); normals map forward as A^-T n
    // (normalize afterwards), which keeps mirrored instances' normals outward.
    double inv[3][3];
    double det;  // det A (negative for a mirroring transform)
};

// A^-1 of the linear part of `m` (12 floats, row-major), or nothing when the rule above
// rejects it. The inverse is the adjugate over the determinant (Cramer's rule).
inline std::optional<LinearInverse> invert_linear(const float* m) {
    for (int i = 0; i < 12; ++i)
        if (!std::isfinite(m[i])) return std::nullopt;
    double a[3][3];
    double scale = 0;
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            a[r][c] = m[4 * r + c];
            scale = std::max(scale, std::fabs(a[r][c]));
        }
    LinearInverse out;
    out.det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) -
              a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0]) +
              a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    if (!(std::fabs(out.det) > 1e-12 * scale * scale * scale)) return std::nullopt;
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            const int r1 = (c + 1) % 3, r2 = (c + 2) % 3, c1 = (r + 1) % 3, c2 = (r + 2) % 3;
            out.inv[r][c] = (a[r1][c1] * a[r2][c2] - a[r1][c2] * a[r2][c1]) / out.det;
        }
    return out;
}

// The normal matrix A^-T as 9 floats, row-major (n_world = N n_object, then normalize).
inline std::array<float, 9> normal_matrix(const LinearInverse& li) {
    std::array<float, 9> n{};
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) n[3 * r + c] = float(li.inv[c][r]);
    return n;
}

}  // namespace lsnif::base
