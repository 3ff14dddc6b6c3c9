// Images for `lsnif eval` (docs/architecture.md §5, "Images"): the float RGB image type, the sRGB
// transfer functions, PSNR, the FLIP error heat map and PNG writing.
//
// Encoding convention: an Image holds display values in [0, 1]. Whether they are
// sRGB-encoded or linear is a property of where the image came from, so every function
// below states what it expects: FLIP (flip.hpp), psnr() and heatmap()'s output are
// sRGB-encoded; write_png() takes the encoding as an argument; a renderer's radiance is
// linear and goes through to_srgb() (or linear_to_srgb() per value) first.
//
// Contract: nothing here throws, exits or prints. Fallible calls return a Result
// (result.hpp) whose message names the offending file or argument.
#pragma once

#include <lsnif/image/result.hpp>

#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace lsnif::image {

// Row-major from the top row, 3 interleaved channels (R, G, B) per pixel:
// rgb[3 * (y * width + x) + c]. A well-formed image has rgb.size() == 3 * width * height;
// the functions below check this and report a mismatch instead of reading out of bounds.
struct Image {
    std::uint32_t width = 0;
    std::uint32_t height = 0;
    std::vector<float> rgb;
};

enum class Encoding : std::uint8_t {
    srgb,    // values are sRGB-encoded (IEC 61966-2-1), i.e. what a display shows
    linear,  // values are linear (proportional to light); sRGB-encoded on output
};

// IEC 61966-2-1 (sRGB) transfer functions, the exact piecewise form:
//   linear = v / 12.92                     for v <= 0.04045
//          = ((v + 0.055) / 1.055)^2.4     otherwise
// and its inverse (threshold 0.0031308). Arguments are clamped to [0, 1] first (NaN
// becomes 0), so the result is always in [0, 1]: these are LDR display values.
double srgb_to_linear(double v) noexcept;
double linear_to_srgb(double v) noexcept;
float srgb_to_linear(float v) noexcept;
float linear_to_srgb(float v) noexcept;

// Whole-image versions (per value, same clamping).
Image to_srgb(Image linear);
Image to_linear(Image srgb);

// Peak signal-to-noise ratio in dB of `test` against `reference`, over all three channels
// of sRGB-encoded values clamped to [0, 1] (peak 1): PSNR = 10 log10(1 / MSE).
// Identical images give +infinity (std::numeric_limits<double>::infinity()); callers that
// need a finite number (JSON has no infinity) choose their own cap or null. Returns NaN
// when the images cannot be compared (different or inconsistent sizes, empty, or a
// non-finite value); flip() on the same pair reports why.
double psnr(const Image& reference, const Image& test);

// FLIP's error visualisation: each value of `error` (row-major, width x height, in
// [0, 1]; clamped, NaN shown as 1 so it stands out) mapped to a colour of a magma-like,
// perceptually ordered map (dark purple-black for 0 through red to pale yellow for 1;
// luminance increases monotonically). The FLIP paper shows its error maps with magma.
// Returns an sRGB-encoded image, or an empty image (0 x 0) when error.size() is not
// width * height.
Image heatmap(std::span<const float> error, std::uint32_t width, std::uint32_t height);

// Writes `image` as an 8-bit RGB PNG (sRGB-encoded, no gamma chunk: viewers assume sRGB).
// `encoding` says what the values are: linear values are sRGB-encoded first. Values are
// clamped to [0, 1] (NaN as 0) and rounded to the nearest of 0..255.
//
// The file appears complete or not at all: the PNG is written to a temporary file in the
// same directory and renamed over `path` (replacing an existing file). On failure the
// temporary file is removed and the error names `path` (or the temporary file) and the
// reason. The directory must exist.
Result<void> write_png(const std::string& path, const Image& image, Encoding encoding = Encoding::srgb);

}  // namespace lsnif::image
