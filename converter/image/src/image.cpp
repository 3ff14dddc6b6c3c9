// Image helpers for `lsnif eval`: sRGB transfer, PSNR, the heat map and PNG writing
// (image.hpp has the contracts).
#include <lsnif/image/image.hpp>

#include "internal.hpp"

#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <climits>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <new>
#include <system_error>

namespace lsnif::image {

namespace internal {

std::string shape_problem(const Image& image) {
    const std::string size = " (" + std::to_string(image.width) + " x " + std::to_string(image.height) + ")";
    if (image.width == 0 || image.height == 0) return "is empty" + size;
    const std::uint64_t expected = 3ull * image.width * image.height;
    if (image.rgb.size() != expected)
        return "has " + std::to_string(image.rgb.size()) + " values, expected " + std::to_string(expected) +
               " for 3 channels" + size;
    return {};
}

std::string non_finite_problem(const Image& image) {
    for (std::size_t i = 0; i < image.rgb.size(); ++i) {
        const float v = image.rgb[i];
        if (std::isfinite(v)) continue;
        const std::size_t pixel = i / 3;
        const std::uint64_t width = std::max<std::uint32_t>(image.width, 1);
        const char* kind = std::isnan(v) ? "nan" : v > 0 ? "+inf" : "-inf";
        return std::string("has a non-finite value (") + kind + ") at pixel (" +
               std::to_string(pixel % width) + ", " + std::to_string(pixel / width) + "), channel " +
               "RGB"[i % 3];
    }
    return {};
}

}  // namespace internal

namespace {

// Clamps to [0, 1]; NaN becomes 0 (std::clamp would pass NaN through).
template <class T>
T unit_clamp(T v) {
    return v > T(0) ? (v < T(1) ? v : T(1)) : T(0);
}

}  // namespace

// IEC 61966-2-1:1999 (sRGB) decoding and encoding. The linear segment near black avoids
// the infinite slope of a pure power law; the thresholds 0.04045 / 0.0031308 are the
// standard's (the two pieces meet there to within 1e-7).
double srgb_to_linear(double v) noexcept {
    v = unit_clamp(v);
    return v <= 0.04045 ? v / 12.92 : std::pow((v + 0.055) / 1.055, 2.4);
}

double linear_to_srgb(double v) noexcept {
    v = unit_clamp(v);
    return v <= 0.0031308 ? 12.92 * v : 1.055 * std::pow(v, 1.0 / 2.4) - 0.055;
}

float srgb_to_linear(float v) noexcept {
    return static_cast<float>(srgb_to_linear(static_cast<double>(v)));
}
float linear_to_srgb(float v) noexcept {
    return static_cast<float>(linear_to_srgb(static_cast<double>(v)));
}

Image to_srgb(Image linear) {
    for (float& v : linear.rgb) v = linear_to_srgb(v);
    return linear;
}

Image to_linear(Image srgb) {
    for (float& v : srgb.rgb) v = srgb_to_linear(v);
    return srgb;
}

double psnr(const Image& reference, const Image& test) {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    if (!internal::shape_problem(reference).empty() || !internal::shape_problem(test).empty()) return kNaN;
    if (reference.width != test.width || reference.height != test.height) return kNaN;
    double sum = 0.0;
    for (std::size_t i = 0; i < reference.rgb.size(); ++i) {
        const float r = reference.rgb[i], t = test.rgb[i];
        if (!std::isfinite(r) || !std::isfinite(t)) return kNaN;
        const double d = static_cast<double>(unit_clamp(r)) - static_cast<double>(unit_clamp(t));
        sum += d * d;
    }
    if (sum == 0.0) return std::numeric_limits<double>::infinity();
    const double mse = sum / static_cast<double>(reference.rgb.size());
    return 10.0 * std::log10(1.0 / mse);
}

Image heatmap(std::span<const float> error, std::uint32_t width, std::uint32_t height) {
    // Nine evenly spaced samples of matplotlib's "magma" (van der Walt & Smith, 2015), as
    // sRGB bytes, interpolated linearly in sRGB. The FLIP paper shows its error maps in
    // magma: perceptually ordered (luminance rises monotonically from black to pale
    // yellow), so brighter always means a larger error, also in greyscale print.
    static constexpr std::array<std::array<float, 3>, 9> kMagma = {{
        {0x00, 0x00, 0x04},
        {0x1D, 0x11, 0x47},
        {0x51, 0x12, 0x7C},
        {0x82, 0x26, 0x81},
        {0xB6, 0x36, 0x79},
        {0xE6, 0x51, 0x64},
        {0xFB, 0x88, 0x61},
        {0xFE, 0xC2, 0x87},
        {0xFC, 0xFD, 0xBF},
    }};
    Image out;
    if (static_cast<std::uint64_t>(width) * height != error.size()) return out;
    out.width = width;
    out.height = height;
    out.rgb.resize(3 * error.size());
    constexpr int kSegments = static_cast<int>(kMagma.size()) - 1;
    for (std::size_t p = 0; p < error.size(); ++p) {
        const float e = std::isnan(error[p]) ? 1.0f : unit_clamp(error[p]);
        const float s = e * kSegments;
        const int i = std::min(static_cast<int>(s), kSegments - 1);
        const float f = s - static_cast<float>(i);
        for (int c = 0; c < 3; ++c) {
            const float lo = kMagma[i][c], hi = kMagma[i + 1][c];
            out.rgb[3 * p + c] = (lo + f * (hi - lo)) / 255.0f;
        }
    }
    return out;
}

namespace {

std::string errno_message(int err) {
    return std::generic_category().message(err);
}

Result<void> write_png_unchecked_alloc(const std::string& path, const Image& image, Encoding encoding) {
    if (path.empty()) return Error{"write_png: empty path"};
    if (const std::string problem = internal::shape_problem(image); !problem.empty())
        return Error{path + ": image " + problem};
    // stb_image_write sizes its buffers with int: rows of 3 w bytes plus a filter byte.
    if (image.width > (INT_MAX - 1) / 3 ||
        (3ull * image.width + 1) * image.height > static_cast<std::uint64_t>(INT_MAX))
        return Error{path + ": image too large for the PNG writer (" + std::to_string(image.width) + " x " +
                     std::to_string(image.height) + ")"};

    std::vector<std::uint8_t> bytes(image.rgb.size());
    for (std::size_t i = 0; i < bytes.size(); ++i) {
        const float v =
            encoding == Encoding::linear ? linear_to_srgb(image.rgb[i]) : unit_clamp(image.rgb[i]);
        bytes[i] = static_cast<std::uint8_t>(std::lround(v * 255.0f));
    }
    std::vector<unsigned char> png;
    if (!internal::encode_png(bytes.data(), static_cast<int>(image.width), static_cast<int>(image.height),
                              png))
        return Error{path + ": PNG encoding failed (out of memory)"};

    // A name no other writer uses (process id, per-process counter), in the target's
    // directory so the rename stays within one file system and is atomic.
    static std::atomic<std::uint64_t> counter{0};
    const std::string tmp = path + ".tmp." + std::to_string(static_cast<long long>(::getpid())) + "." +
                            std::to_string(counter.fetch_add(1));
    // "x": fail rather than truncate a file that already has this name.
    std::FILE* file = std::fopen(tmp.c_str(), "wbx");
    if (!file) {
        const int err = errno;
        return Error{path + ": cannot create temporary file '" + tmp + "': " + errno_message(err)};
    }
    bool ok = std::fwrite(png.data(), 1, png.size(), file) == png.size();
    int err = ok ? 0 : errno;
    if (std::fclose(file) != 0 && ok) {  // buffered data is flushed (and may fail) here
        ok = false;
        err = errno;
    }
    std::error_code ec;
    if (!ok) {
        std::filesystem::remove(tmp, ec);
        return Error{path + ": cannot write: " + errno_message(err)};
    }
    std::filesystem::rename(tmp, path, ec);
    if (ec) {
        std::error_code ignored;
        std::filesystem::remove(tmp, ignored);
        return Error{path + ": cannot move the temporary file into place: " + ec.message()};
    }
    return {};
}

}  // namespace

Result<void> write_png(const std::string& path, const Image& image, Encoding encoding) {
    try {
        return write_png_unchecked_alloc(path, image, encoding);
    } catch (const std::bad_alloc&) {
        // The temporary file is only created after the last allocation that can fail
        // (the error strings are built after it is removed), so nothing is left behind.
        return Error{path + ": out of memory"};
    }
}

}  // namespace lsnif::image
