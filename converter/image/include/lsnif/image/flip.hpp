// LDR-FLIP, our own implementation from the paper's equations: P. Andersson, J. Nilsson,
// T. Akenine-Möller, M. Oskarsson, K. Åström, M. D. Fairchild, "FLIP: A Difference
// Evaluator for Alternating Images", Proc. ACM Comput. Graph. Interact. Tech. 3(2), 2020
// (HPG 2020). FLIP predicts how visible the difference between two images is to an observer flipping
// between them, per pixel, as a value in [0, 1].
//
// Pipeline (flip.cpp has every formula next to its code; comments there cite the paper's
// algorithm subsections as [colour: ...], [feature: ...], [final]):
//   colour pipeline:  sRGB -> linear RGB -> XYZ (D65) -> YyCxCz; per-channel contrast
//                     sensitivity filters (sums of Gaussians); back to linear RGB, clamped
//                     to [0, 1]; CIELAB; Hunt adjustment; HyAB distance; power qc and
//                     compression into [0, 1] against the largest distance (Hunt-adjusted
//                     green vs blue) -> ΔEc
//   feature pipeline: luminance Y/Yn; edge (1st) and point (2nd derivative of Gaussian)
//                     detectors; larger magnitude difference / sqrt 2, power qf -> ΔEf
//   final map:        ΔE = ΔEc^(1 - ΔEf)
//
// Inputs are sRGB-encoded images with values in [0, 1] (values outside are clamped; use
// to_srgb() on linear renders). Borders are handled by clamp-to-edge (the nearest edge
// pixel is repeated), so a flat image stays flat after every filter.
//
// Contract: never throws, exits or prints; single-threaded; deterministic (the same inputs
// give bit-identical output). Cost: O(w h (r_c + r_f)) with r_c, r_f the filter radii
// below (separable filters), dominated by pow/cbrt of the per-pixel colour conversions
// (bench_flip measures it).
#pragma once

#include <lsnif/image/image.hpp>
#include <lsnif/image/result.hpp>

#include <span>
#include <vector>

namespace lsnif::image {

// The paper's constants.
inline constexpr double kFlipQc = 0.7;   // colour-distance exponent
inline constexpr double kFlipPc = 0.4;   // compression knee, fraction of the maximal distance
inline constexpr double kFlipPt = 0.95;  // compressed value at the knee
inline constexpr double kFlipQf = 0.5;   // feature-difference exponent
inline constexpr double kFlipW = 0.082;  // feature width in degrees; σ = 0.5 w PPD pixels

// Limits of FlipOptions::pixels_per_degree: below 1 a pixel spans more than a degree
// (meaningless for an image) and the detector kernels underflow; above 1000 the filters
// grow past 130 pixels of radius for no display anyone uses.
inline constexpr double kFlipMinPixelsPerDegree = 1.0;
inline constexpr double kFlipMaxPixelsPerDegree = 1000.0;

struct FlipOptions {
    // Pixels per degree of visual angle. The paper's default: a 0.7 m wide 3840-pixel
    // monitor seen from 0.7 m, ≈ 67. Higher means finer pixels (or a more distant
    // observer): the filters widen and fine differences fade. Must lie in
    // [kFlipMinPixelsPerDegree, kFlipMaxPixelsPerDegree].
    double pixels_per_degree = 67.0;
    // Also return the colour and feature components (FlipResult::color_error,
    // feature_error); off by default to save 2 x 4 bytes per pixel.
    bool keep_components = false;
};

// Pooled statistics of the error map. Percentiles interpolate linearly between the
// order statistics at rank q (n - 1) (the common "type 7" definition, NumPy's default).
struct FlipStats {
    double mean = 0.0;
    double median = 0.0;
    double p95 = 0.0;
    double max = 0.0;
};

// The statistics of any set of per-pixel errors (an error map, or the pixels of one
// object pooled over several views); `errors` must not be empty.
FlipStats error_stats(std::span<const float> errors);

struct FlipResult {
    std::vector<float> error_map;  // ΔE per pixel, row-major, width x height, in [0, 1]
    FlipStats stats;
    // With FlipOptions::keep_components only (empty otherwise), same layout:
    std::vector<float> color_error;    // ΔEc in [0, 1], colour pipeline
    std::vector<float> feature_error;  // ΔEf in [0, 1], feature pipeline
};

// FLIP of `test` against `reference` (both sRGB-encoded, same size). Errors (message
// names the problem): size mismatch, empty image, rgb.size() != 3 w h, a non-finite
// value (with its image, pixel and channel), pixels_per_degree out of range.
Result<FlipResult> flip(const Image& reference, const Image& test, const FlipOptions& options = {});

// ---------------------------------------------------------------------------------------
// Building blocks of the colour pipeline, exposed so single colours can be compared and
// so the tests can check each formula on its own. `linear` values are linear RGB in
// [0, 1] (clamped); CIELAB is relative to the D65 white of the sRGB primaries (the XYZ of
// linear RGB (1, 1, 1)), so white is L* = 100, a* = b* = 0.

struct Lab {
    double L = 0.0, a = 0.0, b = 0.0;
};

Lab lab_from_linear_rgb(double r, double g, double b) noexcept;

// Colour pipeline, Hunt effect (chroma looks weaker at low luminance): a*, b* scaled by
// 0.01 L*.
Lab hunt_adjust(const Lab& c) noexcept;

// Colour pipeline, HyAB distance (Abasi et al. 2020): city-block in L*, Euclidean in (a*, b*).
double hyab(const Lab& x, const Lab& y) noexcept;

// Colour pipeline: the maximal colour distance, HyAB between Hunt-adjusted pure green and pure
// blue raised to qc (≈ 41.28).
double flip_max_color_distance() noexcept;

// Colour pipeline, compression: maps d = HyAB^qc in [0, cmax] to [0, 1]: linearly [0, pc cmax] -> [0, pt],
// then [pc cmax, cmax] -> [pt, 1] (larger distances are compressed: once a difference is
// obvious, how obvious matters less). Clamped to [0, 1].
double flip_compress_color_distance(double d) noexcept;

// ΔEc of two unfiltered colours: Hunt-adjusted CIELAB, HyAB, qc, compression. Equals
// flip()'s colour error between two flat images of these colours.
double flip_color_error(double r0, double g0, double b0, double r1, double g1, double b1) noexcept;

}  // namespace lsnif::image
