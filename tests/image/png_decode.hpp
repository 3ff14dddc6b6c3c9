// Test helper: decodes a PNG with stb_image (an independent reader of what write_png
// wrote). Only the tests use it.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace lsnif::image::testing {

struct DecodedPng {
    int width = 0, height = 0, channels = 0;  // channels as stored in the file
    std::vector<std::uint8_t> rgb;            // 3 bytes per pixel, row-major; empty on failure
};

DecodedPng decode_png(const std::string& path);

}  // namespace lsnif::image::testing
