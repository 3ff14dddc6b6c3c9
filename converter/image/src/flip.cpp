// LDR-FLIP, written from the paper (Andersson et al. 2020; flip.hpp has the reference and
// the contract). Comments cite the paper's parts as [colour: ...], [feature: ...] and
// [final], the names of its algorithm subsections (colour pipeline, feature pipeline,
// final difference map); every formula is written out next to the code that uses it.
//
// Numerics: images are float planes, kernels are built in double and stored as float,
// per-pixel colour conversions run in double. Filters are separable (every 2-D kernel
// here is a product g(x) g(y) or a sum of two such products) and handle borders by
// clamp-to-edge; symmetric and antisymmetric kernels are applied in paired form so that a
// flat region gives exactly zero feature response.
#include <lsnif/image/flip.hpp>

#include "internal.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <new>
#include <numbers>
#include <string>
#include <vector>

namespace lsnif::image {
namespace {

using Mat3 = std::array<std::array<double, 3>, 3>;
using Vec3 = std::array<double, 3>;

// Linear sRGB -> CIE XYZ for the sRGB primaries and D65 white (IEC 61966-2-1; the
// 7-digit form of the matrix).
constexpr Mat3 kRgbToXyz = {{
    {0.4124564, 0.3575761, 0.1804375},
    {0.2126729, 0.7151522, 0.0721750},
    {0.0193339, 0.1191920, 0.9503041},
}};

constexpr Mat3 invert(const Mat3& m) {
    const double c00 = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    const double c01 = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    const double c02 = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    const double inv_det = 1.0 / (m[0][0] * c00 + m[0][1] * c01 + m[0][2] * c02);
    return {{
        {c00 * inv_det, (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * inv_det,
         (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * inv_det},
        {c01 * inv_det, (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * inv_det,
         (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * inv_det},
        {c02 * inv_det, (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * inv_det,
         (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * inv_det},
    }};
}

// The exact inverse of the matrix above (not the separately rounded published one), so a
// colour survives RGB -> XYZ -> RGB to ~1e-16.
constexpr Mat3 kXyzToRgb = invert(kRgbToXyz);

// Reference white: the XYZ of linear RGB (1, 1, 1), i.e. D65 as the sRGB primaries
// reproduce it. Normalizing by it maps white to L* = 100, a* = b* = 0 exactly.
constexpr Vec3 kWhite = {kRgbToXyz[0][0] + kRgbToXyz[0][1] + kRgbToXyz[0][2],
                         kRgbToXyz[1][0] + kRgbToXyz[1][1] + kRgbToXyz[1][2],
                         kRgbToXyz[2][0] + kRgbToXyz[2][1] + kRgbToXyz[2][2]};

constexpr Vec3 mul(const Mat3& m, const Vec3& v) {
    return {m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
            m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
            m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2]};
}

template <class T>
T unit_clamp(T v) {
    return v > T(0) ? (v < T(1) ? v : T(1)) : T(0);
}

// CIELAB's compressive function (CIE 15:2004): cube root above (6/29)^3, linear below.
double lab_f(double t) {
    constexpr double d = 6.0 / 29.0;
    return t > d * d * d ? std::cbrt(t) : t / (3.0 * d * d) + 4.0 / 29.0;
}

// --- Filters ---------------------------------------------------------------------------

enum class Symmetry : std::uint8_t {
    even,           // k(-i) = k(i)
    odd,            // k(-i) = -k(i), k(0) = 0
    even_zero_sum,  // even, and k(0) = -2 sum_{i>0} k(i) (the kernel sums to zero)
};

// A 1-D kernel on offsets -radius..radius, stored by its half: w[i] is the weight at +i.
// Responses are correlations, R(x) = sum_i k(i) I(x + i), evaluated in paired form:
//   even:           w0 I(x) + sum_{i>0} w_i (I(x+i) + I(x-i))
//   odd:            sum_{i>0} w_i (I(x+i) - I(x-i))
//   even_zero_sum:  sum_{i>0} w_i (I(x+i) + I(x-i) - 2 I(x))
// The last two are exactly 0 on a constant signal whatever the rounding of the weights,
// so flat regions have no spurious features (ΔEf^qf would amplify 1e-8 to 1e-4).
struct Kernel {
    std::vector<float> w;
    Symmetry symmetry = Symmetry::even;
    std::size_t radius() const { return w.size() - 1; }
};

void init_output(float* dst, const float* center, std::size_t n, const Kernel& k) {
    if (k.symmetry == Symmetry::even) {
        const float w0 = k.w[0];
        for (std::size_t x = 0; x < n; ++x) dst[x] = w0 * center[x];
    } else {
        std::fill_n(dst, n, 0.0f);
    }
}

void add_tap(float* __restrict dst, const float* center, const float* plus, const float* minus, std::size_t n,
             float w, Symmetry symmetry) {
    switch (symmetry) {
        case Symmetry::even:
            for (std::size_t x = 0; x < n; ++x) dst[x] += w * (plus[x] + minus[x]);
            break;
        case Symmetry::odd:
            for (std::size_t x = 0; x < n; ++x) dst[x] += w * (plus[x] - minus[x]);
            break;
        case Symmetry::even_zero_sum:
            for (std::size_t x = 0; x < n; ++x) dst[x] += w * ((plus[x] + minus[x]) - 2.0f * center[x]);
            break;
    }
}

// A width x height plane, row-major.
struct Plane {
    std::size_t width = 0, height = 0;
    std::vector<float> v;
    Plane() = default;
    Plane(std::size_t w, std::size_t h) : width(w), height(h), v(w * h) {}
    float* row(std::size_t y) { return v.data() + y * width; }
    const float* row(std::size_t y) const { return v.data() + y * width; }
};

// Horizontal pass. Clamp-to-edge: each row is copied into a buffer padded with `radius`
// copies of its first and last pixel.
void filter_rows(const Plane& in, Plane& out, const Kernel& k, std::vector<float>& padded) {
    const std::size_t r = k.radius(), w = in.width;
    padded.resize(w + 2 * r);
    for (std::size_t y = 0; y < in.height; ++y) {
        const float* src = in.row(y);
        std::fill_n(padded.begin(), r, src[0]);
        std::copy(src, src + w, padded.begin() + static_cast<std::ptrdiff_t>(r));
        std::fill_n(padded.begin() + static_cast<std::ptrdiff_t>(r + w), r, src[w - 1]);
        const float* c = padded.data() + r;
        float* dst = out.row(y);
        init_output(dst, c, w, k);
        for (std::size_t i = 1; i <= r; ++i) add_tap(dst, c, c + i, c - i, w, k.w[i], k.symmetry);
    }
}

// Vertical pass, a row at a time (contiguous, vectorizable). Clamp-to-edge: rows above
// the top and below the bottom are the first and last row.
void filter_cols(const Plane& in, Plane& out, const Kernel& k) {
    const std::size_t r = k.radius(), w = in.width;
    const std::ptrdiff_t last = static_cast<std::ptrdiff_t>(in.height) - 1;
    for (std::ptrdiff_t y = 0; y <= last; ++y) {
        float* dst = out.row(static_cast<std::size_t>(y));
        const float* center = in.row(static_cast<std::size_t>(y));
        init_output(dst, center, w, k);
        for (std::size_t i = 1; i <= r; ++i) {
            const auto di = static_cast<std::ptrdiff_t>(i);
            const float* plus = in.row(static_cast<std::size_t>(std::min(y + di, last)));
            const float* minus = in.row(static_cast<std::size_t>(std::max<std::ptrdiff_t>(y - di, 0)));
            add_tap(dst, center, plus, minus, w, k.w[i], k.symmetry);
        }
    }
}

// --- [colour: spatial filtering] --------------------------------------------------------
// Each YyCxCz channel is filtered with its contrast sensitivity function, modelled in the
// frequency domain (f in cycles per degree) as a sum of Gaussians
//     S^(f) = a1 exp(-b1 f^2) + a2 exp(-b2 f^2),
// whose spatial form (x in degrees, r = |(x, y)|) is
//     S(r) = a1 sqrt(pi / b1) exp(-pi^2 r^2 / b1) + a2 sqrt(pi / b2) exp(-pi^2 r^2 / b2).
// The paper's constants (a2 = 0: a single Gaussian):
struct CsfChannel {
    double a1, b1, a2, b2;
};
constexpr std::array<CsfChannel, 3> kCsf = {{
    {1.0, 0.0047, 0.0, 1e-5},   // achromatic (Yy)
    {1.0, 0.0053, 0.0, 1e-5},   // red-green (Cx)
    {34.1, 0.04, 13.5, 0.025},  // blue-yellow (Cz)
}};

// One term c * (g (x) g) of a channel's 2-D kernel, g normalized to sum 1.
struct CsfTerm {
    double weight;
    Kernel g;
};

// The 2-D kernel, sampled at pixel centres (x = offset / PPD degrees) on a square of
// radius r = ceil(3 sigma_max PPD), sigma_max the largest standard deviation of any
// Gaussian above (sigma = sqrt(b / (2 pi^2)), from b1 = 0.04: 0.045 degrees, r = 10 pixels
// at 67 PPD), and normalized to sum 1 (a flat image stays flat). Each Gaussian term is
// separable, so the kernel is sum_t c_t g_t(x) g_t(y) with
//     g_t = G_t / sum G_t,   c_t = A_t (sum G_t)^2 / sum_t' A_t' (sum G_t')^2,
// A_t = a_t sqrt(pi / b_t) and G_t(i) = exp(-pi^2 (i / PPD)^2 / b_t) the sampled Gaussian.
// The amplitude is the paper's (the 1-D transform's a sqrt(pi / b), evaluated at the 2-D
// radius). It only matters for blue-yellow, the one channel with two terms: it mixes them
// about a1 sqrt(b1) : a2 sqrt(b2), where the 2-D transform's a pi / b would give a1 : a2.
// test_flip.cpp pins this choice with a blue-yellow grating.
std::array<std::vector<CsfTerm>, 3> csf_kernels(double ppd) {
    constexpr double pi = std::numbers::pi;
    double b_max = 0.0;
    for (const CsfChannel& c : kCsf) b_max = std::max({b_max, c.b1, c.a2 > 0.0 ? c.b2 : 0.0});
    const auto r = static_cast<std::size_t>(std::ceil(3.0 * std::sqrt(b_max / (2.0 * pi * pi)) * ppd));
    std::array<std::vector<CsfTerm>, 3> out;
    for (std::size_t ch = 0; ch < 3; ++ch) {
        struct Raw {
            double amplitude, sum;
            std::vector<double> g;
        };
        std::vector<Raw> raw;
        for (const auto& [a, b] :
             {std::pair{kCsf[ch].a1, kCsf[ch].b1}, std::pair{kCsf[ch].a2, kCsf[ch].b2}}) {
            if (a == 0.0) continue;
            Raw t{a * std::sqrt(pi / b), 0.0, std::vector<double>(r + 1)};
            for (std::size_t i = 0; i <= r; ++i) {
                const double x = static_cast<double>(i) / ppd;
                t.g[i] = std::exp(-pi * pi * x * x / b);
                t.sum += i == 0 ? t.g[i] : 2.0 * t.g[i];
            }
            raw.push_back(std::move(t));
        }
        double total = 0.0;
        for (const Raw& t : raw) total += t.amplitude * t.sum * t.sum;
        for (const Raw& t : raw) {
            CsfTerm term{t.amplitude * t.sum * t.sum / total, {}};
            term.g.w.resize(r + 1);
            for (std::size_t i = 0; i <= r; ++i) term.g.w[i] = static_cast<float>(t.g[i] / t.sum);
            out[ch].push_back(std::move(term));
        }
    }
    return out;
}

void filter_channel(const Plane& in, Plane& out, const std::vector<CsfTerm>& terms, Plane& tmp, Plane& acc,
                    std::vector<float>& padded) {
    for (std::size_t t = 0; t < terms.size(); ++t) {
        filter_rows(in, tmp, terms[t].g, padded);
        if (t == 0) {
            filter_cols(tmp, out, terms[t].g);
            if (terms.size() > 1) {
                const auto c = static_cast<float>(terms[t].weight);
                for (float& v : out.v) v *= c;
            }
        } else {
            filter_cols(tmp, acc, terms[t].g);
            const auto c = static_cast<float>(terms[t].weight);
            for (std::size_t i = 0; i < out.v.size(); ++i) out.v[i] += c * acc.v[i];
        }
    }
}

// --- [feature: edge and point detection] ------------------------------------------------
// Detectors are the first and second partial derivatives of a 2-D Gaussian with standard
// deviation sigma = 0.5 w PPD pixels (w = 0.082 degrees), on a square of radius
// ceil(3 sigma). Along x (y symmetric):
//     edge:  dG/dx     = -(x / sigma^2) G(x, y)
//     point: d2G/dx2   = (x^2 / sigma^2 - 1) / sigma^2 G(x, y)
// Each kernel is normalized so that its positive weights sum to 1 and its negative weights
// to -1; then a response to an image in [0, 1] lies in [-1, 1] and a magnitude (the norm
// of the x and y responses) in [0, sqrt 2], which is why the feature difference is divided
// by sqrt 2. With G(x, y) = g(x) g(y), g >= 0, normalizing the 2-D kernel h(x) g(y) that
// way is normalizing h's positive and negative halves separately and g to sum 1, so all
// four detectors stay separable.
struct FeatureKernels {
    Kernel gauss;   // g / sum g
    Kernel first;   // dg/dx, halves normalized to +1 / -1 (odd)
    Kernel second;  // d2g/dx2, halves normalized to +1 / -1 (even, zero sum)
};

Result<FeatureKernels> feature_kernels(double ppd) {
    const double sigma = 0.5 * kFlipW * ppd;
    const auto r = static_cast<std::size_t>(std::ceil(3.0 * sigma));
    const double s2 = sigma * sigma;
    std::vector<double> g(r + 1), d1(r + 1), d2(r + 1);
    double g_sum = 0.0, d1_positive = 0.0, d2_positive = 0.0, d2_negative = 0.0;
    for (std::size_t i = 0; i <= r; ++i) {
        const double x = static_cast<double>(i);
        const double copies = i == 0 ? 1.0 : 2.0;  // offsets +i and -i
        g[i] = std::exp(-x * x / (2.0 * s2));
        d1[i] = -x / s2 * g[i];
        d2[i] = (x * x / s2 - 1.0) / s2 * g[i];
        g_sum += copies * g[i];
        d1_positive += -d1[i];  // the positive half of the odd kernel is at -i
        (d2[i] > 0.0 ? d2_positive : d2_negative) += copies * d2[i];
    }
    if (!(g_sum > 0.0 && d1_positive > 0.0 && d2_positive > 0.0 && d2_negative < 0.0))
        return Error{"pixels_per_degree " + std::to_string(ppd) + " gives degenerate feature kernels"};
    FeatureKernels k;
    k.gauss.w.resize(r + 1);
    k.first.w.resize(r + 1);
    k.second.w.resize(r + 1);
    k.first.symmetry = Symmetry::odd;
    k.second.symmetry = Symmetry::even_zero_sum;
    for (std::size_t i = 0; i <= r; ++i) {
        k.gauss.w[i] = static_cast<float>(g[i] / g_sum);
        k.first.w[i] = static_cast<float>(d1[i] / d1_positive);
        k.second.w[i] = static_cast<float>(d2[i] > 0.0 ? d2[i] / d2_positive : d2[i] / -d2_negative);
    }
    return k;
}

// Edge magnitude |(Gx * L, Gy * L)| and point magnitude |(Gxx * L, Gyy * L)| of a
// luminance plane, with Gx = first(x) gauss(y), Gy = gauss(x) first(y), and likewise for
// the second derivative: three horizontal and four vertical passes.
void feature_magnitudes(const Plane& lum, const FeatureKernels& k, Plane& edge, Plane& point,
                        std::vector<float>& padded) {
    Plane rows_g(lum.width, lum.height), rows_d1(lum.width, lum.height), rows_d2(lum.width, lum.height);
    Plane a(lum.width, lum.height), b(lum.width, lum.height);
    filter_rows(lum, rows_g, k.gauss, padded);
    filter_rows(lum, rows_d1, k.first, padded);
    filter_rows(lum, rows_d2, k.second, padded);
    filter_cols(rows_d1, a, k.gauss);  // d/dx
    filter_cols(rows_g, b, k.first);   // d/dy
    // Plain sqrt, not hypot: responses are bounded by 1, nothing can overflow.
    for (std::size_t i = 0; i < a.v.size(); ++i) edge.v[i] = std::sqrt(a.v[i] * a.v[i] + b.v[i] * b.v[i]);
    filter_cols(rows_d2, a, k.gauss);  // d2/dx2
    filter_cols(rows_g, b, k.second);  // d2/dy2
    for (std::size_t i = 0; i < a.v.size(); ++i) point.v[i] = std::sqrt(a.v[i] * a.v[i] + b.v[i] * b.v[i]);
}

// --- Per-image preparation ---------------------------------------------------------------

// [colour: opponent space] sRGB in [0, 1] -> linear RGB -> XYZ -> YyCxCz, the linearized
// CIELAB the paper filters in (no cube root, so filtering acts on quantities linear in
// light):
//     Yy = 116 Y/Yn - 16,   Cx = 500 (X/Xn - Y/Yn),   Cz = 200 (Y/Yn - Z/Zn).
// [feature: luminance] The feature pipeline works on the achromatic channel normalized to
// [0, 1], (Yy + 16) / 116 = Y / Yn (the paper's erratum corrects its "division by 100" to
// 116), of the unfiltered image.
struct Opponent {
    std::array<Plane, 3> channel;  // Yy, Cx, Cz
    Plane luminance;               // Y / Yn in [0, 1]
};

Opponent to_opponent(const Image& image) {
    const std::size_t w = image.width, h = image.height;
    Opponent o{{Plane(w, h), Plane(w, h), Plane(w, h)}, Plane(w, h)};
    for (std::size_t p = 0; p < w * h; ++p) {
        const Vec3 rgb = {srgb_to_linear(static_cast<double>(image.rgb[3 * p])),
                          srgb_to_linear(static_cast<double>(image.rgb[3 * p + 1])),
                          srgb_to_linear(static_cast<double>(image.rgb[3 * p + 2]))};
        const Vec3 xyz = mul(kRgbToXyz, rgb);
        const double x = xyz[0] / kWhite[0], y = xyz[1] / kWhite[1], z = xyz[2] / kWhite[2];
        o.channel[0].v[p] = static_cast<float>(116.0 * y - 16.0);
        o.channel[1].v[p] = static_cast<float>(500.0 * (x - y));
        o.channel[2].v[p] = static_cast<float>(200.0 * (y - z));
        o.luminance.v[p] = static_cast<float>(y);
    }
    return o;
}

// [colour: back to RGB] Filtered YyCxCz -> XYZ -> linear RGB, clamped to [0, 1] (filtering
// can leave the gamut; the paper clamps before the perceptual colour space), then the
// Hunt-adjusted CIELAB of the result.
Lab filtered_to_hunt_lab(float yy, float cx, float cz) {
    const double y = (static_cast<double>(yy) + 16.0) / 116.0;
    const double x = y + static_cast<double>(cx) / 500.0;
    const double z = y - static_cast<double>(cz) / 200.0;
    const Vec3 rgb = mul(kXyzToRgb, {x * kWhite[0], y * kWhite[1], z * kWhite[2]});
    return hunt_adjust(lab_from_linear_rgb(rgb[0], rgb[1], rgb[2]));
}

FlipStats stats_of(std::span<const float> e) {
    FlipStats s;
    double sum = 0.0;
    for (float v : e) sum += v;
    s.mean = sum / static_cast<double>(e.size());
    s.max = *std::max_element(e.begin(), e.end());
    // Order statistics by selection (O(n) rather than a full sort's O(n log n)). The 95th
    // percentile is selected first; the median then only needs the lower part.
    std::vector<float> v(e.begin(), e.end());
    const auto percentile = [&v](double q, std::size_t end) {
        const double pos = q * static_cast<double>(v.size() - 1);
        const auto lo = static_cast<std::size_t>(pos);
        const auto at = v.begin() + static_cast<std::ptrdiff_t>(lo);
        std::nth_element(v.begin(), at, v.begin() + static_cast<std::ptrdiff_t>(end));
        const double frac = pos - static_cast<double>(lo);
        if (frac == 0.0 || lo + 1 >= v.size()) return static_cast<double>(*at);
        // The next order statistic is the smallest element after `at`.
        const float next = *std::min_element(at + 1, v.end());
        return static_cast<double>(*at) + frac * (static_cast<double>(next) - *at);
    };
    s.p95 = percentile(0.95, v.size());
    s.median = percentile(0.5, static_cast<std::size_t>(0.95 * static_cast<double>(v.size() - 1)) + 1);
    return s;
}

Result<FlipResult> flip_checked(const Image& reference, const Image& test, const FlipOptions& options) {
    if (const std::string p = internal::shape_problem(reference); !p.empty())
        return Error{"reference image " + p};
    if (const std::string p = internal::shape_problem(test); !p.empty()) return Error{"test image " + p};
    if (reference.width != test.width || reference.height != test.height)
        return Error{"image sizes differ: reference " + std::to_string(reference.width) + " x " +
                     std::to_string(reference.height) + ", test " + std::to_string(test.width) + " x " +
                     std::to_string(test.height)};
    if (const std::string p = internal::non_finite_problem(reference); !p.empty())
        return Error{"reference image " + p};
    if (const std::string p = internal::non_finite_problem(test); !p.empty()) return Error{"test image " + p};
    const double ppd = options.pixels_per_degree;
    if (!(ppd >= kFlipMinPixelsPerDegree && ppd <= kFlipMaxPixelsPerDegree))
        return Error{"pixels_per_degree must be in [" + std::to_string(kFlipMinPixelsPerDegree) + ", " +
                     std::to_string(kFlipMaxPixelsPerDegree) + "], got " + std::to_string(ppd)};
    Result<FeatureKernels> features = feature_kernels(ppd);
    if (!features) return features.error();

    const std::size_t w = reference.width, h = reference.height, n = w * h;
    Opponent ref = to_opponent(reference), tst = to_opponent(test);

    // [colour: spatial filtering] per channel, both images.
    const std::array<std::vector<CsfTerm>, 3> csf = csf_kernels(ppd);
    std::vector<float> padded;
    {
        Plane filtered(w, h), tmp(w, h), acc(w, h);
        for (Opponent* o : {&ref, &tst}) {
            for (std::size_t ch = 0; ch < 3; ++ch) {
                filter_channel(o->channel[ch], filtered, csf[ch], tmp, acc, padded);
                std::swap(o->channel[ch], filtered);
            }
        }
    }

    FlipResult result;
    result.error_map.resize(n);
    if (options.keep_components) {
        result.color_error.resize(n);
        result.feature_error.resize(n);
    }

    // [feature] magnitudes of both images; the planes are reused for ΔEf below.
    Plane edge_ref(w, h), point_ref(w, h), edge_tst(w, h), point_tst(w, h);
    feature_magnitudes(ref.luminance, *features, edge_ref, point_ref, padded);
    feature_magnitudes(tst.luminance, *features, edge_tst, point_tst, padded);

    for (std::size_t p = 0; p < n; ++p) {
        // [colour: Hunt, HyAB, power, compression] ΔEc in [0, 1].
        const Lab a = filtered_to_hunt_lab(ref.channel[0].v[p], ref.channel[1].v[p], ref.channel[2].v[p]);
        const Lab b = filtered_to_hunt_lab(tst.channel[0].v[p], tst.channel[1].v[p], tst.channel[2].v[p]);
        const double color = flip_compress_color_distance(std::pow(hyab(a, b), kFlipQc));

        // [feature: difference] ΔEf = (max(|Δedge|, |Δpoint|) / sqrt 2)^qf in [0, 1].
        const double d_edge = std::fabs(static_cast<double>(edge_ref.v[p]) - edge_tst.v[p]);
        const double d_point = std::fabs(static_cast<double>(point_ref.v[p]) - point_tst.v[p]);
        const double scaled = std::max(d_edge, d_point) / std::numbers::sqrt2;
        static_assert(kFlipQf == 0.5, "the square root below is the power qf");
        const double feature = unit_clamp(std::sqrt(scaled));

        // [final] ΔE = ΔEc^(1 - ΔEf): features sharpen (raise) a colour error, never create
        // one where the colours agree unless the features differ completely (0^0 = 1).
        const double error = feature == 0.0 ? color : std::pow(color, 1.0 - feature);
        result.error_map[p] = static_cast<float>(unit_clamp(error));
        if (options.keep_components) {
            result.color_error[p] = static_cast<float>(color);
            result.feature_error[p] = static_cast<float>(feature);
        }
    }
    result.stats = stats_of(result.error_map);
    return result;
}

}  // namespace

Lab lab_from_linear_rgb(double r, double g, double b) noexcept {
    const Vec3 xyz = mul(kRgbToXyz, {unit_clamp(r), unit_clamp(g), unit_clamp(b)});
    const double fx = lab_f(xyz[0] / kWhite[0]), fy = lab_f(xyz[1] / kWhite[1]),
                 fz = lab_f(xyz[2] / kWhite[2]);
    return {116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)};
}

// [colour: Hunt effect] chroma is perceived as weaker at low luminance: a*, b* scaled by
// 0.01 L* (1 at white, 0 at black).
Lab hunt_adjust(const Lab& c) noexcept {
    return {c.L, 0.01 * c.L * c.a, 0.01 * c.L * c.b};
}

// [colour: HyAB] HyAB(x, y) = |L1 - L2| + sqrt((a1 - a2)^2 + (b1 - b2)^2), which the paper
// prefers to the Euclidean CIELAB distance for large colour differences.
double hyab(const Lab& x, const Lab& y) noexcept {
    const double da = x.a - y.a, db = x.b - y.b;  // |a*|, |b*| < 200: no overflow, no hypot needed
    return std::fabs(x.L - y.L) + std::sqrt(da * da + db * db);
}

// [colour: normalization] cmax = HyAB(Hunt(green), Hunt(blue))^qc, the largest distance
// between two Hunt-adjusted colours of the RGB cube.
double flip_max_color_distance() noexcept {
    static const double cmax = std::pow(hyab(hunt_adjust(lab_from_linear_rgb(0.0, 1.0, 0.0)),
                                             hunt_adjust(lab_from_linear_rgb(0.0, 0.0, 1.0))),
                                        kFlipQc);
    return cmax;
}

// [colour: compression] with d = HyAB^qc:
//     ΔEc = (pt / (pc cmax)) d                                   if d < pc cmax
//         = pt + (d - pc cmax) / (cmax - pc cmax) (1 - pt)       otherwise
double flip_compress_color_distance(double d) noexcept {
    const double cmax = flip_max_color_distance(), knee = kFlipPc * cmax;
    const double e = d < knee ? kFlipPt / knee * d : kFlipPt + (d - knee) / (cmax - knee) * (1.0 - kFlipPt);
    return unit_clamp(e);
}

double flip_color_error(double r0, double g0, double b0, double r1, double g1, double b1) noexcept {
    const double d =
        hyab(hunt_adjust(lab_from_linear_rgb(r0, g0, b0)), hunt_adjust(lab_from_linear_rgb(r1, g1, b1)));
    return flip_compress_color_distance(std::pow(d, kFlipQc));
}

Result<FlipResult> flip(const Image& reference, const Image& test, const FlipOptions& options) {
    try {
        return flip_checked(reference, test, options);
    } catch (const std::bad_alloc&) {
        return Error{"out of memory for FLIP on " + std::to_string(reference.width) + " x " +
                     std::to_string(reference.height) + " images"};
    }
}

FlipStats error_stats(std::span<const float> errors) {
    return stats_of(errors);
}

}  // namespace lsnif::image
