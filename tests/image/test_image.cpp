// lsnif::image images: sRGB transfer functions against the standard's values, PSNR by
// hand, the heat map's ordering, and PNG writing checked byte by byte and by decoding the
// file with an independent reader (stb_image).
#include <lsnif/image/image.hpp>

#include "png_decode.hpp"

#include <doctest/doctest.h>
#include "../test_data.hpp"

#include <array>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <string>
#include <vector>

using namespace lsnif::image;
namespace fs = std::filesystem;

namespace {

// A fresh, empty directory for one test case.
fs::path work_dir(const std::string& name) {
    return lsnif::test::fresh_dir(LSNIF_IMAGE_WORK_DIR, name);
}

std::vector<std::string> entries(const fs::path& dir) {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(dir)) names.push_back(e.path().filename().string());
    return names;
}

std::vector<unsigned char> read_bytes(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

std::uint32_t be32(const std::vector<unsigned char>& b, std::size_t at) {
    return std::uint32_t(b[at]) << 24 | std::uint32_t(b[at + 1]) << 16 | std::uint32_t(b[at + 2]) << 8 |
           b[at + 3];
}

double luminance_of_srgb(const float* rgb) {
    return 0.2126729 * srgb_to_linear(double(rgb[0])) + 0.7151522 * srgb_to_linear(double(rgb[1])) +
           0.0721750 * srgb_to_linear(double(rgb[2]));
}

// A 5 x 3 image whose every value is distinct and known.
Image gradient() {
    Image im{5, 3, std::vector<float>(45)};
    for (std::size_t i = 0; i < im.rgb.size(); ++i) im.rgb[i] = static_cast<float>(i) / 44.0f;
    return im;
}

}  // namespace

TEST_CASE("sRGB transfer functions: the standard's values, continuity, round trip, clamping") {
    CHECK(srgb_to_linear(0.0) == 0.0);
    CHECK(srgb_to_linear(1.0) == doctest::Approx(1.0).epsilon(1e-15));
    CHECK(srgb_to_linear(0.04045) == doctest::Approx(0.04045 / 12.92));
    CHECK(srgb_to_linear(0.5) == doctest::Approx(std::pow(0.555 / 1.055, 2.4)));  // 0.214041
    CHECK(srgb_to_linear(0.5) == doctest::Approx(0.2140411).epsilon(1e-6));
    CHECK(linear_to_srgb(0.0031308) == doctest::Approx(0.04045).epsilon(1e-4));
    CHECK(linear_to_srgb(0.2140411) == doctest::Approx(0.5).epsilon(1e-6));
    // The two pieces meet at the thresholds (to the standard's 1e-7-ish rounding).
    CHECK(std::abs(std::pow((0.04045 + 0.055) / 1.055, 2.4) - 0.04045 / 12.92) < 1e-7);
    CHECK(std::abs(srgb_to_linear(0.04045 + 1e-12) - srgb_to_linear(0.04045)) < 1e-7);
    CHECK(std::abs(linear_to_srgb(0.0031308 + 1e-12) - linear_to_srgb(0.0031308)) < 1e-7);
    // Round trips, double and float.
    for (int i = 0; i <= 10000; ++i) {
        const double v = i / 10000.0;
        CHECK(linear_to_srgb(srgb_to_linear(v)) == doctest::Approx(v).epsilon(1e-12));
        CHECK(srgb_to_linear(linear_to_srgb(v)) == doctest::Approx(v).epsilon(1e-12));
        const float f = static_cast<float>(v);
        CHECK(std::abs(linear_to_srgb(srgb_to_linear(f)) - f) < 2e-6f);
    }
    // Every 8-bit code survives decode + encode + rounding.
    for (int c = 0; c < 256; ++c) CHECK(std::lround(linear_to_srgb(srgb_to_linear(c / 255.0)) * 255) == c);
    // Monotonic.
    for (int i = 1; i <= 1000; ++i) CHECK(srgb_to_linear(i / 1000.0) > srgb_to_linear((i - 1) / 1000.0));
    // Clamped to [0, 1]; NaN becomes 0.
    CHECK(srgb_to_linear(-0.5) == 0.0);
    CHECK(srgb_to_linear(3.0) == doctest::Approx(1.0));
    CHECK(linear_to_srgb(std::numeric_limits<double>::quiet_NaN()) == 0.0);
    CHECK(linear_to_srgb(2.0f) == doctest::Approx(1.0f));
    // Whole images.
    const Image lin = to_linear(gradient());
    const Image back = to_srgb(lin);
    for (std::size_t i = 0; i < back.rgb.size(); ++i)
        CHECK(back.rgb[i] == doctest::Approx(gradient().rgb[i]));
    CHECK(lin.rgb[22] == doctest::Approx(srgb_to_linear(0.5f)));
}

TEST_CASE("PSNR: +inf for identical images, hand-computed values, NaN for invalid pairs") {
    const Image a = gradient();
    CHECK(psnr(a, a) == std::numeric_limits<double>::infinity());
    // Each value 0.1 away from a grey 0.5 in one channel only: MSE = 0.01 / 3, so
    // PSNR = 10 log10(300) = 24.7712 dB.
    Image grey{4, 4, std::vector<float>(48, 0.5f)};
    Image off = grey;
    for (std::size_t p = 0; p < 16; ++p) off.rgb[3 * p + 1] = p % 2 ? 0.6f : 0.4f;
    CHECK(psnr(grey, off) == doctest::Approx(24.771213).epsilon(1e-6));
    CHECK(psnr(off, grey) == psnr(grey, off));
    // Black vs white: MSE 1, 0 dB. Values outside [0, 1] are clamped first.
    Image black{2, 2, std::vector<float>(12, 0.0f)}, white{2, 2, std::vector<float>(12, 1.0f)};
    CHECK(psnr(black, white) == doctest::Approx(0.0));
    Image whiter{2, 2, std::vector<float>(12, 7.0f)};
    CHECK(psnr(black, whiter) == doctest::Approx(0.0));
    CHECK(psnr(white, whiter) == std::numeric_limits<double>::infinity());
    // Invalid pairs.
    CHECK(std::isnan(psnr(a, black)));
    CHECK(std::isnan(psnr(Image{}, Image{})));
    Image nan = a;
    nan.rgb[7] = std::numeric_limits<float>::quiet_NaN();
    CHECK(std::isnan(psnr(a, nan)));
    Image ragged = a;
    ragged.rgb.push_back(0.0f);
    CHECK(std::isnan(psnr(ragged, ragged)));
}

TEST_CASE("heat map: magma end points, monotonically rising luminance, clamping, bad sizes") {
    std::vector<float> ramp(1001);
    for (std::size_t i = 0; i < ramp.size(); ++i) ramp[i] = static_cast<float>(i) / 1000.0f;
    const Image map = heatmap(ramp, 1001, 1);
    REQUIRE(map.width == 1001);
    REQUIRE(map.height == 1);
    REQUIRE(map.rgb.size() == 3 * 1001);
    // Magma starts near black (0, 0, 4) and ends pale yellow (252, 253, 191).
    CHECK(map.rgb[0] == doctest::Approx(0 / 255.0));
    CHECK(map.rgb[2] == doctest::Approx(4 / 255.0));
    CHECK(map.rgb[3 * 1000] == doctest::Approx(252 / 255.0));
    CHECK(map.rgb[3 * 1000 + 1] == doctest::Approx(253 / 255.0));
    CHECK(map.rgb[3 * 1000 + 2] == doctest::Approx(191 / 255.0));
    // The control points themselves, at t = k / 8: matplotlib magma's samples.
    const int magma[9][3] = {{0x00, 0x00, 0x04}, {0x1D, 0x11, 0x47}, {0x51, 0x12, 0x7C},
                             {0x82, 0x26, 0x81}, {0xB6, 0x36, 0x79}, {0xE6, 0x51, 0x64},
                             {0xFB, 0x88, 0x61}, {0xFE, 0xC2, 0x87}, {0xFC, 0xFD, 0xBF}};
    for (int k = 0; k <= 8; ++k)
        for (int c = 0; c < 3; ++c) CHECK(map.rgb[3 * (125 * k) + c] == doctest::Approx(magma[k][c] / 255.0));
    // Halfway between two control points (t = 1.5 / 8): their average.
    const std::vector<float> half = {0.1875f};
    const Image mid = heatmap(half, 1, 1);
    for (int c = 0; c < 3; ++c)
        CHECK(mid.rgb[c] == doctest::Approx((magma[1][c] + magma[2][c]) / 2.0 / 255.0));
    // Perceptually ordered: a larger error is always a brighter colour.
    for (std::size_t i = 1; i < ramp.size(); ++i)
        CHECK(luminance_of_srgb(&map.rgb[3 * i]) > luminance_of_srgb(&map.rgb[3 * (i - 1)]));
    for (float v : map.rgb) {
        CHECK(v >= 0.0f);
        CHECK(v <= 1.0f);
    }
    // Clamping: below 0 is 0, above 1 is 1; NaN is shown as the maximum.
    const std::vector<float> odd = {-1.0f, 0.0f, 2.0f, 1.0f, std::numeric_limits<float>::quiet_NaN(), 1.0f};
    const Image m = heatmap(odd, 3, 2);
    REQUIRE(m.rgb.size() == 18);
    for (int c = 0; c < 3; ++c) {
        CHECK(m.rgb[c] == m.rgb[3 + c]);
        CHECK(m.rgb[6 + c] == m.rgb[9 + c]);
        CHECK(m.rgb[12 + c] == m.rgb[15 + c]);
    }
    // Size mismatch: an empty image, not a read past the end.
    const Image bad = heatmap(ramp, 10, 10);
    CHECK(bad.width == 0);
    CHECK(bad.height == 0);
    CHECK(bad.rgb.empty());
}

TEST_CASE("write_png writes a valid 8-bit RGB PNG, atomically, with the right pixels") {
    const fs::path dir = work_dir("png_ok");
    const fs::path file = dir / "gradient.png";
    const Image im = gradient();
    const auto w = write_png(file.string(), im);
    REQUIRE_MESSAGE(w.ok(), w.error().message);
    // Only the file itself: the temporary file was renamed, not left behind.
    CHECK(entries(dir) == std::vector<std::string>{"gradient.png"});

    const std::vector<unsigned char> bytes = read_bytes(file);
    REQUIRE(bytes.size() > 33);
    const unsigned char signature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};
    CHECK(std::equal(signature, signature + 8, bytes.begin()));
    CHECK(be32(bytes, 8) == 13);  // IHDR chunk length
    CHECK(std::string(bytes.begin() + 12, bytes.begin() + 16) == "IHDR");
    CHECK(be32(bytes, 16) == 5);  // width
    CHECK(be32(bytes, 20) == 3);  // height
    CHECK(int(bytes[24]) == 8);   // bit depth
    CHECK(int(bytes[25]) == 2);   // colour type: truecolour RGB
    CHECK(std::string(bytes.end() - 8, bytes.end() - 4) == "IEND");

    // An independent decoder reads back round(v * 255) for every value.
    const testing::DecodedPng png = testing::decode_png(file.string());
    REQUIRE(png.rgb.size() == im.rgb.size());
    CHECK(png.width == 5);
    CHECK(png.height == 3);
    CHECK(png.channels == 3);
    for (std::size_t i = 0; i < im.rgb.size(); ++i) CHECK(int(png.rgb[i]) == std::lround(im.rgb[i] * 255.0f));
}

TEST_CASE("write_png: linear input is sRGB-encoded, out-of-range values are clamped, files are replaced") {
    const fs::path dir = work_dir("png_linear");
    const fs::path file = dir / "out.png";
    Image im{2, 1, {0.5f, 0.0031308f, 1.0f, -3.0f, 7.0f, std::numeric_limits<float>::quiet_NaN()}};
    // NaN is not a valid pixel for FLIP, but the writer must not choke on it: it writes 0.
    REQUIRE(write_png(file.string(), im, Encoding::linear));
    testing::DecodedPng png = testing::decode_png(file.string());
    REQUIRE(png.rgb.size() == 6);
    CHECK(int(png.rgb[0]) == std::lround(linear_to_srgb(0.5) * 255));  // 188, not 128
    CHECK(int(png.rgb[0]) == 188);
    CHECK(int(png.rgb[1]) == 10);  // 0.04045 * 255
    CHECK(int(png.rgb[2]) == 255);
    CHECK(int(png.rgb[3]) == 0);
    CHECK(int(png.rgb[4]) == 255);
    CHECK(int(png.rgb[5]) == 0);

    // Writing again replaces the file in place.
    REQUIRE(write_png(file.string(), Image{1, 1, {0.0f, 1.0f, 0.0f}}));
    png = testing::decode_png(file.string());
    CHECK(png.width == 1);
    CHECK(png.rgb == std::vector<std::uint8_t>{0, 255, 0});
    CHECK(entries(dir) == std::vector<std::string>{"out.png"});
}

TEST_CASE("write_png failures name the path and leave nothing behind") {
    const fs::path dir = work_dir("png_fail");
    const fs::path missing = dir / "no_such_dir" / "image.png";
    const auto r = write_png(missing.string(), gradient());
    REQUIRE_FALSE(r.ok());
    CAPTURE(r.error().message);
    CHECK(r.error().message.find(missing.string()) == 0);
    CHECK(r.error().message.find("No such file or directory") != std::string::npos);
    CHECK_FALSE(fs::exists(dir / "no_such_dir"));
    CHECK(entries(dir).empty());

    // Malformed images: reported with the path, nothing created.
    const fs::path file = dir / "bad.png";
    for (const Image& bad : {Image{}, Image{2, 2, std::vector<float>(11)}}) {
        const auto b = write_png(file.string(), bad);
        REQUIRE_FALSE(b.ok());
        CAPTURE(b.error().message);
        CHECK(b.error().message.find(file.string() + ": image ") == 0);
    }
    CHECK(write_png("", gradient()).error().message == "write_png: empty path");
    // The target is a directory: the rename fails, the temporary file is removed.
    fs::create_directories(dir / "taken.png");
    const auto t = write_png((dir / "taken.png").string(), gradient());
    REQUIRE_FALSE(t.ok());
    CAPTURE(t.error().message);
    CHECK(t.error().message.find((dir / "taken.png").string()) == 0);
    CHECK(entries(dir) == std::vector<std::string>{"taken.png"});
    CHECK(fs::is_empty(dir / "taken.png"));
}
