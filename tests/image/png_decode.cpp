// stb_image's implementation for the tests only (PNG only, internal linkage).
#include "png_decode.hpp"

#define STB_IMAGE_STATIC
#define STB_IMAGE_IMPLEMENTATION
#define STBI_ONLY_PNG
#include <stb/stb_image.h>

namespace lsnif::image::testing {

DecodedPng decode_png(const std::string& path) {
    DecodedPng out;
    unsigned char* data = stbi_load(path.c_str(), &out.width, &out.height, &out.channels, 3);
    if (!data) return out;
    out.rgb.assign(data, data + static_cast<std::size_t>(out.width) * out.height * 3);
    stbi_image_free(data);
    return out;
}

}  // namespace lsnif::image::testing
