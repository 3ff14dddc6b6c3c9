// Hand-written Adam (Kingma & Ba 2015, Algorithm 1, with the bias correction folded into
// the step size as in §2 of the paper):
//   m <- b1 m + (1-b1) g ;  v <- b2 v + (1-b2) g^2
//   p <- p - lr * sqrt(1-b2^t)/(1-b1^t) * m / (sqrt(v) + eps)
// Hash-table rows are updated sparsely, only in steps where they received gradient, each
// with its own step counter t (as tiny-cuda-nn / instant-ngp do), so a rarely touched row
// gets correctly bias-corrected steps instead of being shrunk by a global t.
#pragma once

#include <lsnif/base/math.hpp>

#include <cmath>
#include <cstddef>
#include <cstdint>

namespace lsnif::trainer {

struct AdamConfig {
    float lr;
    float beta1;
    float beta2;
    float eps;
    float l2;  // decoupled-from-nothing L2 penalty: g += l2 * p before the moments
};

// The bias-corrected step factor of step t (t >= 1): sqrt(1 - b2^t) / (1 - b1^t). Sparse
// hash-row updates look it up in a table (Trainer) instead of computing two powers per row
// in the hot loop; same double arithmetic, so the same float step either way.
// The powers by repeated squaring (base::pow_int): the same bits on every machine.
inline double adam_bias_correction(const AdamConfig& c, std::uint32_t t) {
    const double bc1 = 1.0 - base::pow_int(double(c.beta1), t);
    const double bc2 = 1.0 - base::pow_int(double(c.beta2), t);
    return std::sqrt(bc2) / bc1;
}

// One parameter's Adam step with an already bias-corrected step size: the arithmetic every
// update below shares. Returns the new parameter and moments.
struct AdamState {
    float p, m, v;
};
inline AdamState adam_step(float p, float m, float v, float g, float step, float grad_scale,
                           const AdamConfig& c) {
    const float gi = g * grad_scale + c.l2 * p;
    const float mi = c.beta1 * m + (1.0f - c.beta1) * gi;
    const float vi = c.beta2 * v + (1.0f - c.beta2) * gi * gi;
    return {p - step * mi / (std::sqrt(vi) + c.eps), mi, vi};
}

// Updates n parameters with an already bias-corrected step size (lr x correction).
inline void adam_update_corrected(float* p, float* m, float* v, const float* g, std::size_t n, float step,
                                  float grad_scale, const AdamConfig& c) {
    for (std::size_t i = 0; i < n; ++i) {
        const AdamState s = adam_step(p[i], m[i], v[i], g[i], step, grad_scale, c);
        p[i] = s.p, m[i] = s.m, v[i] = s.v;
    }
}

// Updates n parameters that share step counter `t` (t >= 1). `lr` already includes any
// schedule; `grad_scale` multiplies g first (gradient clipping).
inline void adam_update(float* p, float* m, float* v, const float* g, std::size_t n, std::uint32_t t,
                        float lr, float grad_scale, const AdamConfig& c) {
    adam_update_corrected(p, m, v, g, n, float(double(lr) * adam_bias_correction(c, t)), grad_scale, c);
}

// Rows of F parameters updated sparsely (a hash-grid level): parameters, moments and this
// step's gradient are rows x F arrays; flags and counters are per row.
struct SparseRows {
    float* p;
    float* m;
    float* v;
    float* g;                 // this step's gradient; active rows are zeroed here
    std::uint8_t* active;     // rows with a gradient this step; cleared here
    std::uint32_t* row_step;  // updates each row has taken (its own bias correction)
    std::uint32_t F;
};

// Sparse Adam (adam_update_corrected's arithmetic) over rows [rb, re): an active row takes a
// step of lr x correction[its new step count] (correction[t] = adam_bias_correction(c, t),
// defined up to the largest count), and its flag and gradient are cleared (the gradient
// table is zero again for the next step's sums); an inactive row keeps its
// parameters and moments. Rows go 32 at a time: the step sizes are spread per element and the update selects
// between old and new values, so the arithmetic vectorizes across rows (a row alone is F = 3
// elements, and most rows are active in every step). Returns the largest |parameter| of the
// rows [rb, re) after the update, NaN if one of them is NaN.
float adam_update_rows(const SparseRows& r, std::size_t rb, std::size_t re, float lr,
                       const double* correction, float grad_scale, const AdamConfig& c);

}  // namespace lsnif::trainer
