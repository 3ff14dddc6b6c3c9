// lsnif::image FLIP: the properties the paper states (zero for identical images, values in
// [0, 1], symmetric, flat colours unaffected by the filters, features only at edges,
// finer pixels hide fine detail) and the colour formulas against values computed by hand
// here from published CIELAB coordinates of the sRGB primaries.
#include <lsnif/image/flip.hpp>

#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <limits>
#include <random>
#include <string>
#include <vector>

using namespace lsnif::image;

namespace {

Image flat(std::uint32_t w, std::uint32_t h, float r, float g, float b) {
    Image im{w, h, {}};
    im.rgb.reserve(3ull * w * h);
    for (std::uint64_t p = 0; p < 1ull * w * h; ++p) im.rgb.insert(im.rgb.end(), {r, g, b});
    return im;
}

Image random_image(std::uint32_t w, std::uint32_t h, std::uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    Image im{w, h, std::vector<float>(3ull * w * h)};
    for (float& v : im.rgb) v = u(rng);
    return im;
}

// Grey vertical step: columns x < edge are `lo`, the rest `hi`.
Image step(std::uint32_t w, std::uint32_t h, std::uint32_t edge, float lo, float hi) {
    Image im{w, h, std::vector<float>(3ull * w * h)};
    for (std::uint32_t y = 0; y < h; ++y)
        for (std::uint32_t x = 0; x < w; ++x)
            for (int c = 0; c < 3; ++c) im.rgb[3 * (std::size_t(y) * w + x) + c] = x < edge ? lo : hi;
    return im;
}

FlipResult run(const Image& a, const Image& b, double ppd = 67.0) {
    FlipOptions opt;
    opt.pixels_per_degree = ppd;
    opt.keep_components = true;
    auto r = flip(a, b, opt);
    REQUIRE_MESSAGE(r.ok(), r.error().message);
    REQUIRE(r->error_map.size() == std::size_t(a.width) * a.height);
    REQUIRE(r->color_error.size() == r->error_map.size());
    REQUIRE(r->feature_error.size() == r->error_map.size());
    return std::move(*r);
}

// Published CIELAB (D65) of the sRGB primaries (e.g. B. Lindbloom's calculator), used as
// the hand reference for the conversion and for cmax.
constexpr Lab kRed{53.2408, 80.0925, 67.2032};
constexpr Lab kGreen{87.7347, -86.1827, 83.1793};
constexpr Lab kBlue{32.2970, 79.1875, -107.8602};

// cmax by hand: Hunt (a*, b* times L*/100) on the published green and blue, HyAB, ^0.7.
double hand_cmax() {
    const double ga = kGreen.a * kGreen.L / 100, gb = kGreen.b * kGreen.L / 100;
    const double ba = kBlue.a * kBlue.L / 100, bb = kBlue.b * kBlue.L / 100;
    const double hyab =
        std::abs(kGreen.L - kBlue.L) + std::sqrt((ga - ba) * (ga - ba) + (gb - bb) * (gb - bb));
    return std::pow(hyab, 0.7);
}

// ΔEc by hand for a HyAB distance d (before the power).
double hand_color_error(double d) {
    const double c = std::pow(d, 0.7), cmax = hand_cmax(), knee = 0.4 * cmax;
    return c < knee ? 0.95 / knee * c : 0.95 + (c - knee) / (cmax - knee) * 0.05;
}

}  // namespace

TEST_CASE("identical images give exactly zero error everywhere") {
    for (const Image& im :
         {random_image(64, 48, 1), step(40, 20, 17, 0.1f, 0.9f), flat(3, 2, 0.3f, 0.6f, 0.9f)}) {
        const FlipResult r = run(im, im);
        CHECK(std::all_of(r.error_map.begin(), r.error_map.end(), [](float v) { return v == 0.0f; }));
        CHECK(std::all_of(r.color_error.begin(), r.color_error.end(), [](float v) { return v == 0.0f; }));
        CHECK(std::all_of(r.feature_error.begin(), r.feature_error.end(), [](float v) { return v == 0.0f; }));
        CHECK(r.stats.mean == 0.0);
        CHECK(r.stats.median == 0.0);
        CHECK(r.stats.p95 == 0.0);
        CHECK(r.stats.max == 0.0);
    }
}

TEST_CASE("every value lies in [0, 1], for ordinary and extreme pairs") {
    // Random content, complementary images, saturated corners of the RGB cube, out-of-range
    // input (clamped), and the two colours the normalization is built from.
    Image inverse = random_image(50, 40, 2);
    Image original = inverse;
    for (float& v : inverse.rgb) v = 1.0f - v;
    Image corners = random_image(50, 40, 3), corners2 = random_image(50, 40, 4);
    for (float& v : corners.rgb) v = v < 0.5f ? 0.0f : 1.0f;
    for (float& v : corners2.rgb) v = v < 0.5f ? 0.0f : 1.0f;
    Image wild = random_image(50, 40, 5);
    for (float& v : wild.rgb) v = 4.0f * v - 2.0f;
    const std::vector<std::pair<Image, Image>> pairs = {
        {random_image(50, 40, 6), random_image(50, 40, 7)},
        {original, inverse},
        {corners, corners2},
        {wild, random_image(50, 40, 8)},
        {flat(50, 40, 0, 1, 0), flat(50, 40, 0, 0, 1)},
        {flat(50, 40, 0, 0, 0), corners},
    };
    double largest = 0;
    for (const auto& [a, b] : pairs) {
        const FlipResult r = run(a, b);
        for (const auto* v : {&r.error_map, &r.color_error, &r.feature_error})
            for (float x : *v) {
                REQUIRE(std::isfinite(x));
                CHECK(x >= 0.0f);
                CHECK(x <= 1.0f);
            }
        largest = std::max(largest, r.stats.max);
    }
    CHECK(largest > 0.9);  // the pairs do reach the top of the range
}

TEST_CASE("FLIP is symmetric: swapping a flat-colour pair changes nothing") {
    const float colours[][3] = {{0.2f, 0.5f, 0.7f}, {0.9f, 0.1f, 0.1f}, {0.05f, 0.05f, 0.05f}, {1, 1, 0}};
    for (const auto& c0 : colours)
        for (const auto& c1 : colours) {
            const Image a = flat(12, 9, c0[0], c0[1], c0[2]), b = flat(12, 9, c1[0], c1[1], c1[2]);
            const FlipResult ab = run(a, b), ba = run(b, a);
            CHECK(ab.color_error == ba.color_error);
            CHECK(ab.error_map == ba.error_map);
        }
    // Also on structured content (the feature pipeline uses |difference| too).
    const Image a = random_image(30, 20, 9), b = random_image(30, 20, 10);
    CHECK(run(a, b).error_map == run(b, a).error_map);
}

TEST_CASE("black vs white: colour error near 1, no feature error, so ΔE = ΔEc") {
    const FlipResult r = run(flat(32, 24, 0, 0, 0), flat(32, 24, 1, 1, 1));
    // By hand: L* 0 vs 100, a* = b* = 0 -> HyAB 100 -> 100^0.7 = 25.12, past the knee
    // (0.4 cmax = 16.51): 0.95 + (25.12 - 16.51) / (41.28 - 16.51) * 0.05 = 0.9674.
    const double expected = hand_color_error(100.0);
    CHECK(expected == doctest::Approx(0.9674).epsilon(1e-4));
    for (std::size_t p = 0; p < r.error_map.size(); ++p) {
        CHECK(r.feature_error[p] == 0.0f);
        CHECK(r.error_map[p] == r.color_error[p]);
        CHECK(r.color_error[p] == doctest::Approx(expected).epsilon(1e-5));
    }
    CHECK(r.stats.mean == doctest::Approx(expected).epsilon(1e-5));
}

TEST_CASE("a flat-colour pair has the same error at every size, equal to the single-colour formula") {
    const float c0[3] = {0.2f, 0.5f, 0.7f}, c1[3] = {0.25f, 0.45f, 0.7f};
    const double single = flip_color_error(srgb_to_linear(double(c0[0])), srgb_to_linear(double(c0[1])),
                                           srgb_to_linear(double(c0[2])), srgb_to_linear(double(c1[0])),
                                           srgb_to_linear(double(c1[1])), srgb_to_linear(double(c1[2])));
    REQUIRE(single > 0.05);
    const std::pair<std::uint32_t, std::uint32_t> sizes[] = {{1, 1}, {1, 9}, {5, 3}, {33, 17}, {128, 96}};
    for (const auto& [w, h] : sizes) {
        CAPTURE(w);
        CAPTURE(h);
        const FlipResult r = run(flat(w, h, c0[0], c0[1], c0[2]), flat(w, h, c1[0], c1[1], c1[2]));
        for (std::size_t p = 0; p < r.error_map.size(); ++p) {
            CHECK(r.feature_error[p] == 0.0f);
            CHECK(r.error_map[p] == doctest::Approx(single).epsilon(1e-5));
        }
    }
}

TEST_CASE("a larger colour difference never gives a smaller FLIP on flat images") {
    const float bases[] = {0.1f, 0.5f, 0.8f};
    for (float base : bases) {
        for (int channel = -1; channel < 3; ++channel) {  // -1: all three (grey)
            CAPTURE(base);
            CAPTURE(channel);
            double previous = 0.0;
            for (int k = 0; k <= 40; ++k) {
                const float d = 0.005f * static_cast<float>(k) * (base > 0.5f ? -1.0f : 1.0f);
                float c[3] = {base, base, base};
                for (int i = 0; i < 3; ++i)
                    if (channel < 0 || channel == i) c[i] += d;
                const FlipResult r = run(flat(4, 4, base, base, base), flat(4, 4, c[0], c[1], c[2]));
                CHECK(r.stats.mean >= previous - 1e-7);
                if (k > 0) CHECK(r.stats.mean > 0.0);
                previous = r.stats.mean;
            }
            CHECK(previous > 0.05);
        }
    }
}

TEST_CASE("a moved or blurred edge gives feature error at the edge and none far from it") {
    // At 67 PPD the feature kernels reach ceil(3 * 0.5 * 0.082 * 67) = 9 pixels and the
    // colour kernels ceil(3 * 0.045 * 67) = 10: beyond that both images are identical and
    // flat, so the error must be exactly 0 there.
    constexpr std::uint32_t W = 96, H = 24, kEdge = 48;
    const Image reference = step(W, H, kEdge, 0.1f, 0.9f);
    Image blurred = reference;  // 5-tap box blur along x
    for (std::uint32_t y = 0; y < H; ++y)
        for (std::uint32_t x = 0; x < W; ++x)
            for (int c = 0; c < 3; ++c) {
                float s = 0;
                for (int dx = -2; dx <= 2; ++dx) {
                    const int xx = std::clamp(int(x) + dx, 0, int(W) - 1);
                    s += reference.rgb[3 * (std::size_t(y) * W + xx) + c];
                }
                blurred.rgb[3 * (std::size_t(y) * W + x) + c] = s / 5.0f;
            }
    const Image moved = step(W, H, kEdge + 2, 0.1f, 0.9f);
    for (const Image* test : std::initializer_list<const Image*>{&moved, &blurred}) {
        const FlipResult r = run(reference, *test);
        for (std::uint32_t y = 0; y < H; ++y) {
            float near_edge = 0;
            for (std::uint32_t x = 0; x < W; ++x) {
                const std::size_t p = std::size_t(y) * W + x;
                if (x >= kEdge - 3 && x <= kEdge + 4) near_edge = std::max(near_edge, r.feature_error[p]);
                if (x + 14 < kEdge || x > kEdge + 16) {
                    CHECK(r.feature_error[p] == 0.0f);
                    CHECK(r.error_map[p] == 0.0f);
                }
            }
            CHECK(near_edge > 0.2f);
        }
        // The feature difference raises the colour error at the edge: ΔEc^(1 - ΔEf) >= ΔEc.
        for (std::size_t p = 0; p < r.error_map.size(); ++p) CHECK(r.error_map[p] >= r.color_error[p]);
    }
}

TEST_CASE("detector normalization: a black/white step has edge response 1 at 67 PPD") {
    // The edge kernel's positive and negative halves each sum to 1 in magnitude, so on the
    // two pixels either side of a 0 -> 1 luminance step its response is exactly 1 (the
    // whole positive half sees 1, the negative half 0); the point response there is at
    // most 0.5. Against a flat image that gives ΔEf = (1 / sqrt 2)^0.5 = 0.8409.
    constexpr std::uint32_t W = 40, H = 8, kEdge = 20;
    const FlipResult r = run(step(W, H, kEdge, 0.0f, 1.0f), flat(W, H, 1, 1, 1));
    const double expected = std::pow(1.0 / std::sqrt(2.0), 0.5);
    for (std::uint32_t y = 0; y < H; ++y) {
        CHECK(r.feature_error[y * W + kEdge - 1] == doctest::Approx(expected).epsilon(1e-5));
        CHECK(r.feature_error[y * W + kEdge] == doctest::Approx(expected).epsilon(1e-5));
    }
    // k pixels past the step (x = edge + k) only the kernel taps reaching over it respond:
    //   edge  = sum_{i>k} i g(i) / sum_{i>0} i g(i)                     (positive half = 1)
    //   point = |sum_{i>k} g2(i)| / (positive sum of g2), g2 = (i^2/s^2 - 1) g(i)
    // with g(i) = exp(-i^2 / (2 s^2)), s = 0.5 * 0.082 * 67 = 2.747 pixels, taps up to
    // ceil(3 s) = 9. ΔEf = (max(edge, point) / sqrt 2)^0.5.
    const double sigma = 0.5 * 0.082 * 67.0;
    const int radius = static_cast<int>(std::ceil(3 * sigma));
    REQUIRE(radius == 9);
    const auto g = [&](int i) { return std::exp(-i * i / (2 * sigma * sigma)); };
    const auto g2 = [&](int i) { return (i * i / (sigma * sigma) - 1) * g(i); };
    double first_half = 0, second_positive = 0;
    for (int i = -radius; i <= radius; ++i) {
        if (i > 0) first_half += i * g(i);
        if (g2(i) > 0) second_positive += g2(i);
    }
    for (int k = 1; k <= radius + 1; ++k) {
        CAPTURE(k);
        double edge = 0, point = 0;
        for (int i = k + 1; i <= radius; ++i) {
            edge += i * g(i) / first_half;
            point += g2(i) / second_positive;
        }
        const double feature = std::sqrt(std::max(edge, std::abs(point)) / std::sqrt(2.0));
        for (std::uint32_t y = 0; y < H; ++y) {
            CHECK(r.feature_error[y * W + kEdge + k] == doctest::Approx(feature).epsilon(1e-4));
            // Mirror image on the dark side: x = edge - 1 - k.
            CHECK(r.feature_error[y * W + kEdge - 1 - k] == doctest::Approx(feature).epsilon(1e-4));
        }
    }
}

TEST_CASE("a firefly at 1 PPD, where every kernel reduces to its central taps") {
    // At 1 PPD the Gaussians are far narrower than a pixel: the smoothing kernels are the
    // identity, the edge kernel is (+1, 0, -1) and the point kernel (1/2, -1, 1/2) along
    // each axis. One white pixel on black, against black:
    //   at the pixel:       Gxx = Gyy = -1, point magnitude sqrt 2 -> ΔEf = 1, and
    //                       ΔEc = black vs white, so ΔE = ΔEc^0 = 1;
    //   at its 4 neighbours: edge magnitude 1 -> ΔEf = 0.8409, ΔEc = 0 -> ΔE = 0;
    //   elsewhere:           nothing.
    constexpr std::uint32_t N = 7, C = 3;
    Image firefly = flat(N, N, 0, 0, 0);
    for (int c = 0; c < 3; ++c) firefly.rgb[3 * (C * N + C) + c] = 1.0f;
    const FlipResult r = run(firefly, flat(N, N, 0, 0, 0), 1.0);
    const double edge = std::pow(1.0 / std::sqrt(2.0), 0.5);
    for (std::uint32_t y = 0; y < N; ++y)
        for (std::uint32_t x = 0; x < N; ++x) {
            CAPTURE(x);
            CAPTURE(y);
            const std::size_t p = y * N + x;
            const int manhattan = std::abs(int(x) - int(C)) + std::abs(int(y) - int(C));
            if (manhattan == 0) {
                CHECK(r.feature_error[p] == doctest::Approx(1.0).epsilon(1e-6));
                CHECK(r.color_error[p] == doctest::Approx(hand_color_error(100)).epsilon(1e-5));
                CHECK(r.error_map[p] == doctest::Approx(1.0).epsilon(1e-5));
            } else if (manhattan == 1) {
                CHECK(r.feature_error[p] == doctest::Approx(edge).epsilon(1e-6));
                CHECK(r.color_error[p] == 0.0f);
                CHECK(r.error_map[p] == 0.0f);
            } else {
                CHECK(r.feature_error[p] == 0.0f);
                CHECK(r.error_map[p] == 0.0f);
            }
        }
}

TEST_CASE("contrast sensitivity filters: each channel attenuates a grating as its CSF says") {
    // A horizontal cosine grating that varies one opponent channel only (an achromatic
    // grating, an X-only red-green one, a Z-only blue-yellow one), compared with the flat
    // colour it oscillates around. Far from the borders the filtered grating's peak is
    // base + amplitude * H(f), where H is the response of the channel's normalized kernel
    // at the grating's frequency; the colour error there follows by hand (CIELAB of the
    // filtered peak, Hunt, HyAB, ^0.7, compression). H is computed here from the paper's
    // CSF: the sampled sum of Gaussians a sqrt(pi / b) exp(-pi^2 x^2 / b), x = i / PPD,
    // radius ceil(3 sqrt(0.04 / (2 pi^2)) PPD), normalized to sum 1 in 2-D; for the
    // single-Gaussian channels it is also checked against the closed form exp(-b f^2).
    constexpr double kPi = 3.14159265358979323846, kPpd = 67.0;
    constexpr std::uint32_t W = 128, H = 6, kPeak = 64;  // kPeak: a multiple of every period
    const int radius = static_cast<int>(std::ceil(3.0 * std::sqrt(0.04 / (2 * kPi * kPi)) * kPpd));
    REQUIRE(radius == 10);
    const auto response = [&](std::vector<std::pair<double, double>> ab, double period) {
        double num = 0, den = 0;
        for (const auto& [a, b] : ab) {
            double sum = 0, cos_sum = 0;
            for (int i = -radius; i <= radius; ++i) {
                const double g = std::exp(-kPi * kPi * (i / kPpd) * (i / kPpd) / b);
                sum += g;
                cos_sum += g * std::cos(2 * kPi * i / period);
            }
            const double weight = a * std::sqrt(kPi / b) * sum * sum;  // this term's 2-D kernel sum
            num += weight * cos_sum / sum;
            den += weight;
        }
        return num / den;
    };
    // The hand pipeline from normalized XYZ (x = X / Xn etc.) to ΔEc against another colour.
    const auto f = [](double t) { return t > 216.0 / 24389 ? std::cbrt(t) : t * 841.0 / 108 + 4.0 / 29; };
    const auto lab = [&](double x, double y, double z) {
        const double L = 116 * f(y) - 16;
        return Lab{L, L / 100 * 500 * (f(x) - f(y)), L / 100 * 200 * (f(y) - f(z))};  // Hunt-adjusted
    };
    const auto hand_error = [&](Lab p, Lab q) {
        return hand_color_error(std::abs(p.L - q.L) + std::hypot(p.a - q.a, p.b - q.b));
    };
    // Published XYZ -> linear sRGB (7 digits) and D65 white, to build the test images.
    constexpr double kToRgb[3][3] = {{3.2404542, -1.5371385, -0.4985314},
                                     {-0.9692660, 1.8760108, 0.0415560},
                                     {0.0556434, -0.2040259, 1.0572252}};
    constexpr double kWhiteXyz[3] = {0.95047, 1.0, 1.08883};
    const auto image_of = [&](double base, int channel, double amplitude, double period) {
        Image im{W, H, std::vector<float>(3 * W * H)};
        for (std::uint32_t x = 0; x < W; ++x) {
            double n[3] = {base, base, base};  // normalized XYZ
            const double d = amplitude * std::cos(2 * kPi * x / period);
            for (int k = 0; k < 3; ++k)
                if (channel < 0 || channel == k) n[k] += d;
            for (int c = 0; c < 3; ++c) {
                double v = 0;
                for (int k = 0; k < 3; ++k) v += kToRgb[c][k] * n[k] * kWhiteXyz[k];
                REQUIRE(v > 0.0);
                REQUIRE(v < 1.0);
                for (std::uint32_t y = 0; y < H; ++y) im.rgb[3 * (y * W + x) + c] = linear_to_srgb(float(v));
            }
        }
        return im;
    };
    struct Case {
        std::string name;
        int channel;  // -1: achromatic (x = y = z vary together); 0: X only; 2: Z only
        double base, amplitude, period;
        std::vector<std::pair<double, double>> csf;  // (a, b) terms of the filtered channel
    };
    const Case cases[] = {
        {"achromatic", -1, 0.3, 0.1, 8, {{1.0, 0.0047}}},
        {"achromatic", -1, 0.3, 0.1, 4, {{1.0, 0.0047}}},
        {"red-green", 0, 0.5, 0.1, 8, {{1.0, 0.0053}}},
        {"red-green", 0, 0.5, 0.1, 16, {{1.0, 0.0053}}},
        {"blue-yellow", 2, 0.5, 0.25, 8, {{34.1, 0.04}, {13.5, 0.025}}},
        {"blue-yellow", 2, 0.5, 0.25, 32, {{34.1, 0.04}, {13.5, 0.025}}},
    };
    for (const Case& c : cases) {
        CAPTURE(c.name);
        CAPTURE(c.period);
        const double h = response(c.csf, c.period);
        if (c.csf.size() == 1) {
            const double freq = kPpd / c.period;  // cycles per degree
            CHECK(h == doctest::Approx(std::exp(-c.csf[0].second * freq * freq)).epsilon(1e-4));
        }
        const double peak = c.base + c.amplitude * h;
        const Lab flat_lab = lab(c.base, c.base, c.base);
        const Lab peak_lab = c.channel < 0    ? lab(peak, peak, peak)
                             : c.channel == 0 ? lab(peak, c.base, c.base)
                                              : lab(c.base, c.base, peak);
        const double expected = hand_error(peak_lab, flat_lab);
        const FlipResult r = run(image_of(c.base, c.channel, c.amplitude, c.period),
                                 flat(W, H, linear_to_srgb(float(c.base)), linear_to_srgb(float(c.base)),
                                      linear_to_srgb(float(c.base))));
        CHECK(expected > 0.02);
        for (std::uint32_t y = 0; y < H; ++y)
            CHECK(r.color_error[y * W + kPeak] == doctest::Approx(expected).epsilon(2e-4));
    }
}

TEST_CASE("Hunt adjustment and HyAB match hand computation") {
    // Hunt: a*, b* times L*/100.
    const Lab x = hunt_adjust({50, 20, -10}), y = hunt_adjust({60, -5, 25});
    CHECK(x.L == 50);
    CHECK(x.a == doctest::Approx(10));
    CHECK(x.b == doctest::Approx(-5));
    CHECK(y.a == doctest::Approx(-3));
    CHECK(y.b == doctest::Approx(15));
    // HyAB: |50 - 60| + sqrt((10 + 3)^2 + (-5 - 15)^2) = 10 + sqrt(569) = 33.8537...
    CHECK(hyab(x, y) == doctest::Approx(33.853720).epsilon(1e-7));
    CHECK(hyab(y, x) == hyab(x, y));
    CHECK(hyab(x, x) == 0.0);
    // A pure lightness difference is counted in full (city block), not as a Euclidean leg.
    CHECK(hyab({30, 3, 4}, {70, 0, 0}) == doctest::Approx(40 + 5));

    // CIELAB of white and the primaries against the published values.
    const Lab white = lab_from_linear_rgb(1, 1, 1);
    CHECK(white.L == doctest::Approx(100).epsilon(1e-9));
    CHECK(std::abs(white.a) < 1e-9);
    CHECK(std::abs(white.b) < 1e-9);
    for (const auto& [lab, rgb] :
         {std::pair{kRed, std::array<double, 3>{1, 0, 0}}, std::pair{kGreen, std::array<double, 3>{0, 1, 0}},
          std::pair{kBlue, std::array<double, 3>{0, 0, 1}}}) {
        const Lab got = lab_from_linear_rgb(rgb[0], rgb[1], rgb[2]);
        CHECK(got.L == doctest::Approx(lab.L).epsilon(2e-5));
        CHECK(got.a == doctest::Approx(lab.a).epsilon(2e-5));
        CHECK(got.b == doctest::Approx(lab.b).epsilon(2e-5));
    }
    // Arguments are linear RGB clamped to [0, 1].
    const Lab clamped = lab_from_linear_rgb(2.0, -1.0, 0.5), inside = lab_from_linear_rgb(1.0, 0.0, 0.5);
    CHECK(clamped.L == inside.L);
    CHECK(clamped.a == inside.a);
    CHECK(clamped.b == inside.b);
    CHECK(flip_color_error(-3, 0.2, 9, 0.5, 0.5, 0.5) == flip_color_error(0, 0.2, 1, 0.5, 0.5, 0.5));
    // cmax by hand from the published green and blue: about 41.28.
    CHECK(hand_cmax() == doctest::Approx(41.2755).epsilon(1e-5));
    CHECK(flip_max_color_distance() == doctest::Approx(hand_cmax()).epsilon(1e-5));
}

TEST_CASE("colour compression: knee at (pc cmax, pt), linear pieces, clamped") {
    const double cmax = flip_max_color_distance(), knee = kFlipPc * cmax;
    CHECK(flip_compress_color_distance(0.0) == 0.0);
    CHECK(flip_compress_color_distance(knee) == doctest::Approx(0.95));
    CHECK(flip_compress_color_distance(knee * (1 - 1e-12)) == doctest::Approx(0.95));  // continuous
    CHECK(flip_compress_color_distance(0.5 * knee) == doctest::Approx(0.475));
    CHECK(flip_compress_color_distance(cmax) == doctest::Approx(1.0));
    CHECK(flip_compress_color_distance(0.5 * (knee + cmax)) == doctest::Approx(0.975));
    CHECK(flip_compress_color_distance(2 * cmax) == 1.0);
    // Pure green vs pure blue is the largest difference: exactly 1.
    CHECK(flip_color_error(0, 1, 0, 0, 0, 1) == doctest::Approx(1.0));
    CHECK(flip_color_error(0, 0, 0, 1, 1, 1) == doctest::Approx(hand_color_error(100)).epsilon(1e-6));
    // Red vs black by hand: HyAB = L* + Hunt chroma = 53.24 + 0.5324 * |(80.09, 67.20)|.
    const double red_black = kRed.L + kRed.L / 100 * std::hypot(kRed.a, kRed.b);
    CHECK(flip_color_error(1, 0, 0, 0, 0, 0) == doctest::Approx(hand_color_error(red_black)).epsilon(1e-5));
}

TEST_CASE("no two colours of the RGB cube are farther apart than green and blue (cmax)") {
    constexpr int kSteps = 7;
    std::vector<Lab> colours;
    for (int r = 0; r < kSteps; ++r)
        for (int g = 0; g < kSteps; ++g)
            for (int b = 0; b < kSteps; ++b)
                colours.push_back(hunt_adjust(
                    lab_from_linear_rgb(r / (kSteps - 1.0), g / (kSteps - 1.0), b / (kSteps - 1.0))));
    const double cmax = flip_max_color_distance();
    double largest = 0;
    for (const Lab& x : colours)
        for (const Lab& y : colours) largest = std::max(largest, std::pow(hyab(x, y), kFlipQc));
    CHECK(largest <= cmax * (1 + 1e-12));
    CHECK(largest == doctest::Approx(cmax));  // and the grid contains green and blue
}

TEST_CASE("more pixels per degree blurs away fine detail") {
    // A one-pixel checkerboard against the flat colour it averages to (in linear light):
    // seen up close (low PPD) the pattern is visible, from afar (high PPD) it is not. Only
    // the interior is compared: clamp-to-edge repeats the border pixel, which turns the
    // checkerboard's border into a coarser pattern that the wider kernels of a high PPD see.
    constexpr std::uint32_t N = 96, kMargin = 24;  // kernel radius at 150 PPD: 21 pixels
    const float lo = 0.2f, hi = 0.8f;
    Image checker{N, N, std::vector<float>(3 * N * N)};
    for (std::uint32_t y = 0; y < N; ++y)
        for (std::uint32_t x = 0; x < N; ++x)
            for (int c = 0; c < 3; ++c) checker.rgb[3 * (y * N + x) + c] = (x + y) % 2 ? hi : lo;
    const float mean = linear_to_srgb(0.5f * (srgb_to_linear(lo) + srgb_to_linear(hi)));
    const Image average = flat(N, N, mean, mean, mean);
    const auto interior_mean = [&](const std::vector<float>& v) {
        double s = 0;
        for (std::uint32_t y = kMargin; y < N - kMargin; ++y)
            for (std::uint32_t x = kMargin; x < N - kMargin; ++x) s += v[y * N + x];
        return s / ((N - 2 * kMargin) * (N - 2 * kMargin));
    };
    std::vector<double> color, total;
    for (double ppd : {5.0, 10.0, 20.0, 40.0, 67.0, 150.0}) {
        CAPTURE(ppd);
        const FlipResult r = run(checker, average, ppd);
        color.push_back(interior_mean(r.color_error));
        total.push_back(interior_mean(r.error_map));
        if (color.size() > 1) {
            CHECK(color.back() <= color[color.size() - 2] + 1e-9);
            CHECK(total.back() <= total[total.size() - 2] + 1e-9);
        }
        // Identical images stay at zero at every PPD.
        CHECK(run(checker, checker, ppd).stats.max == 0.0);
    }
    CHECK(color.front() > 0.5);  // at 5 PPD nothing is filtered away: a large error
    CHECK(total.front() > 0.5);
    CHECK(color.back() < 0.01);  // at 150 PPD the checkerboard is practically uniform
    CHECK(total.back() < 0.05);
}

TEST_CASE("statistics are the mean, type-7 percentiles and max of the error map") {
    const FlipResult r = run(random_image(37, 23, 11), random_image(37, 23, 12));
    std::vector<double> v(r.error_map.begin(), r.error_map.end());
    std::sort(v.begin(), v.end());
    const std::size_t n = v.size();  // 851: odd, so the median is one element
    double sum = 0;
    for (double x : v) sum += x;
    CHECK(r.stats.mean == doctest::Approx(sum / n).epsilon(1e-9));
    CHECK(r.stats.median == v[n / 2]);
    const double pos = 0.95 * (n - 1);  // 807.5
    const auto lo = static_cast<std::size_t>(pos);
    CHECK(r.stats.p95 == doctest::Approx(v[lo] + (pos - lo) * (v[lo + 1] - v[lo])).epsilon(1e-12));
    CHECK(r.stats.max == v.back());
    CHECK(r.stats.max > r.stats.p95);
}

TEST_CASE("FLIP is deterministic and the default options match keep_components") {
    const Image a = random_image(40, 30, 13), b = random_image(40, 30, 14);
    auto plain = flip(a, b);
    REQUIRE(plain);
    CHECK(plain->color_error.empty());
    CHECK(plain->feature_error.empty());
    CHECK(plain->error_map == run(a, b).error_map);
    auto again = flip(a, b);
    REQUIRE(again);
    CHECK(again->error_map == plain->error_map);
}

TEST_CASE("invalid input is reported with a message, never thrown") {
    const Image ok = flat(8, 6, 0.5f, 0.5f, 0.5f);
    const auto fails = [](const Image& a, const Image& b, const std::string& needle, FlipOptions opt = {}) {
        Result<FlipResult> r = flip(a, b, opt);
        REQUIRE_FALSE(r.ok());
        CAPTURE(r.error().message);
        CHECK(r.error().message.find(needle) != std::string::npos);
    };
    fails(ok, flat(6, 8, 0.5f, 0.5f, 0.5f), "reference 8 x 6, test 6 x 8");
    fails(Image{}, ok, "reference image is empty");
    fails(ok, Image{0, 6, {}}, "test image is empty");
    Image short_rgb = ok;
    short_rgb.rgb.pop_back();
    fails(ok, short_rgb, "test image has 143 values, expected 144");
    Image nan = ok;
    nan.rgb[3 * (2 * 8 + 5) + 1] = std::numeric_limits<float>::quiet_NaN();
    fails(nan, ok, "reference image has a non-finite value (nan) at pixel (5, 2), channel G");
    Image inf = ok;
    inf.rgb.back() = -std::numeric_limits<float>::infinity();
    fails(ok, inf, "test image has a non-finite value (-inf) at pixel (7, 5), channel B");
    for (double ppd : {0.0, -67.0, 0.5, 5000.0, std::numeric_limits<double>::quiet_NaN()}) {
        FlipOptions opt;
        opt.pixels_per_degree = ppd;
        fails(ok, ok, "pixels_per_degree must be in", opt);
    }
    // The same images are fine once the problems are gone.
    auto good = flip(ok, ok);
    REQUIRE(good);
    CHECK(good->stats.mean == 0.0);
}
