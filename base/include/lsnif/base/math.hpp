// Elementary functions that give the same bits on every machine: exp, log, log1p, pow, acos,
// sin and cos in double precision, built from +, -, *, / and sqrt alone (IEEE 754 rounds each of
// those exactly), with constants and term orders fixed here. The C library's versions are
// accurate but not reproducible: glibc picks among builds of one routine at run time (with
// and without FMA), and its algorithms change between releases, so the same conversion
// could round differently on another machine or distribution. Everything that reaches an
// asset or a conversion decision (losses, the learning-rate schedule, Adam's bias
// correction, the normal error in degrees) calls these instead (docs/pipeline.md "The same
// bytes everywhere").
//
// Contract: compiled without FMA contraction (-ffp-contract=off, the project's setting:
// CMakeLists.txt), so that a * b + c is two roundings in every build. Accuracy: within a few
// units in the last place of double, far below what float results (which is what callers
// keep) can show. Arguments outside a function's domain give what the C functions give
// (NaN, ±inf, 0); subnormal results are rounded by std::ldexp, which is exact IEEE
// arithmetic too.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

namespace lsnif::base {

namespace detail {

// ln 2 split in two (Cody and Waite, "Software Manual for the Elementary Functions", 1980):
// kLn2Hi has its low 32 bits zero, so k * kLn2Hi is exact for |k| < 2^20.
inline constexpr double kLn2Hi = 6.93147180369123816490e-01;  // 0x3FE62E42FEE00000
inline constexpr double kLn2Lo = 1.90821492927058770002e-10;  // ln 2 - kLn2Hi
inline constexpr double kInvLn2 = 1.44269504088896338700e+00;
inline constexpr double kPi = 3.14159265358979311600e+00;

// e^r for |r| <= ln(2)/2 + a little: the Taylor series to r^14 / 14!, whose remainder is
// below 2^-60 there. Horner's rule, highest term first.
inline double exp_reduced(double r) {
    double p = 1.0 / 87178291200.0;  // 1/14!
    constexpr double inv_fact[] = {1.0 / 6227020800.0,
                                   1.0 / 479001600.0,
                                   1.0 / 39916800.0,
                                   1.0 / 3628800.0,
                                   1.0 / 362880.0,
                                   1.0 / 40320.0,
                                   1.0 / 5040.0,
                                   1.0 / 720.0,
                                   1.0 / 120.0,
                                   1.0 / 24.0,
                                   1.0 / 6.0,
                                   1.0 / 2.0,
                                   1.0,
                                   1.0};
    for (const double c : inv_fact) p = p * r + c;
    return p;
}

// asin(y) for |y| <= 1/2: the Maclaurin series y + (1/2) y^3/3 + (1*3)/(2*4) y^5/5 + ...
// (Abramowitz and Stegun 4.4.40), summed to the term y^61, below 2^-63 relative at |y| = 1/2.
inline double asin_small(double y) {
    const double y2 = y * y;
    double term = y, sum = y;
    double coef = 1.0;  // (1*3*...*(2n-1)) / (2*4*...*2n)
    for (int n = 1; n <= 30; ++n) {
        coef = coef * double(2 * n - 1) / double(2 * n);
        term = term * y2;
        sum = sum + coef * term / double(2 * n + 1);
    }
    return sum;
}

}  // namespace detail

// e^x.
inline double exp(double x) {
    if (x != x) return x;
    if (x > 709.782712893384) return std::numeric_limits<double>::infinity();
    if (x < -745.1332191019412) return 0.0;
    const double k = std::floor(x * detail::kInvLn2 + 0.5);
    const double r = (x - k * detail::kLn2Hi) - k * detail::kLn2Lo;
    return std::ldexp(detail::exp_reduced(r), int(k));
}

// Natural logarithm.
inline double log(double x) {
    if (x != x || x < 0.0) return std::numeric_limits<double>::quiet_NaN();
    if (x == 0.0) return -std::numeric_limits<double>::infinity();
    if (x == std::numeric_limits<double>::infinity()) return x;
    int e = 0;
    double m = std::frexp(x, &e);  // x = m 2^e, m in [1/2, 1): exact
    if (m < 0.70710678118654752440) {
        m = m * 2.0;  // m in [sqrt(1/2), sqrt(2))
        e = e - 1;
    }
    // log m = 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.1716: the series s + s^3/3 + ...
    // to s^41, below 2^-60 relative.
    const double s = (m - 1.0) / (m + 1.0), s2 = s * s;
    double p = 1.0 / 41.0;
    for (int k = 39; k >= 1; k -= 2) p = p * s2 + 1.0 / double(k);
    const double log_m = 2.0 * s * p;
    return (double(e) * detail::kLn2Hi + log_m) + double(e) * detail::kLn2Lo;
}

// log(1 + x), accurate for small x.
inline double log1p(double x) {
    if (x != x || x < -1.0) return std::numeric_limits<double>::quiet_NaN();
    if (std::fabs(x) < 1e-5) return x * (1.0 - x * (0.5 - x / 3.0));
    const double y = 1.0 + x;
    // y rounds x; log(y) corrected by the rounding error (y - 1) - x, to first order.
    return log(y) - ((y - 1.0) - x) / y;
}

// a^b for a > 0 (what the learning-rate schedule needs: exp(b log a)); a = 0 gives 0 for
// b > 0 and 1 for b = 0; a < 0 gives NaN.
inline double pow(double a, double b) {
    if (b == 0.0) return 1.0;
    if (a == 0.0) return b > 0.0 ? 0.0 : std::numeric_limits<double>::infinity();
    return exp(b * log(a));
}

// a^n for an integer n >= 0, by repeated squaring: the bias corrections of Adam.
inline double pow_int(double a, std::uint64_t n) {
    double result = 1.0;
    while (n) {
        if (n & 1u) result = result * a;
        a = a * a;
        n >>= 1;
    }
    return result;
}

// acos(x) in radians for x in [-1, 1] (NaN outside). acos x = pi/2 - asin x for
// |x| <= 1/2, and acos x = 2 asin(sqrt((1 - x) / 2)) (resp. pi - that of -x) beyond, where
// the argument of the series is at most 1/2.
inline double acos(double x) {
    if (x != x || x < -1.0 || x > 1.0) return std::numeric_limits<double>::quiet_NaN();
    if (std::fabs(x) <= 0.5) return detail::kPi / 2.0 - detail::asin_small(x);
    const double a = 2.0 * detail::asin_small(std::sqrt((1.0 - std::fabs(x)) / 2.0));
    return x > 0.0 ? a : detail::kPi - a;
}

namespace detail {

// sin x for |x| <= pi/4: its Taylor series to x^21 (the next term is below 2^-60 x there),
// summed from the smallest term up by Horner's rule.
inline double sin_small(double x) {
    const double x2 = x * x;
    double s = 0.0;
    for (int k = 21; k >= 3; k -= 2) s = (s + 1.0) * (-x2 / double((k - 1) * k));
    return x + x * s;
}

// cos x for |x| <= pi/4: its Taylor series to x^22, the same way.
inline double cos_small(double x) {
    const double x2 = x * x;
    double s = 0.0;
    for (int k = 22; k >= 2; k -= 2) s = (s + 1.0) * (-x2 / double((k - 1) * k));
    return 1.0 + s;
}

// x = q pi/2 + r with |r| <= pi/4 (about: q is the nearest integer to x / (pi/2)), r in two
// parts of pi/2 so that the subtraction is exact for the angles callers use (|x| < 2^20).
inline double reduce_quadrant(double x, std::int64_t& q) {
    constexpr double kPio2Hi = 1.57079632673412561417e+00;  // 0x3FF921FB54400000: pi/2, 33 bits
    constexpr double kPio2Lo = 6.07710050650619224932e-11;  // pi/2 - kPio2Hi
    const double n = std::nearbyint(x * (2.0 / kPi));
    q = std::int64_t(n);
    return (x - n * kPio2Hi) - n * kPio2Lo;
}

}  // namespace detail

// sin and cos in radians, for |x| < 2^20 (camera and light angles; beyond, the reduction
// loses accuracy). NaN for a non-finite argument.
inline double sin(double x) {
    if (!std::isfinite(x)) return std::numeric_limits<double>::quiet_NaN();
    std::int64_t q = 0;
    const double r = detail::reduce_quadrant(x, q);
    switch (q & 3) {
        case 0: return detail::sin_small(r);
        case 1: return detail::cos_small(r);
        case 2: return -detail::sin_small(r);
        default: return -detail::cos_small(r);
    }
}

inline double cos(double x) {
    if (!std::isfinite(x)) return std::numeric_limits<double>::quiet_NaN();
    std::int64_t q = 0;
    const double r = detail::reduce_quadrant(x, q);
    switch (q & 3) {
        case 0: return detail::cos_small(r);
        case 1: return -detail::sin_small(r);
        case 2: return -detail::cos_small(r);
        default: return detail::sin_small(r);
    }
}

}  // namespace lsnif::base
