// Shared by the lsnif::image translation units; not installed, not part of the API.
#pragma once

#include <lsnif/image/image.hpp>

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace lsnif::image::internal {

// Empty when `image` is well formed (non-empty, rgb.size() == 3 w h), else what is wrong,
// e.g. "is empty (0 x 4)". The caller prefixes which image it is.
std::string shape_problem(const Image& image);

// Empty when every value is finite, else e.g. "has a non-finite value (nan) at pixel
// (3, 7), channel G".
std::string non_finite_problem(const Image& image);

// PNG encoding by stb_image_write (compiled with internal linkage in
// stb_image_write_impl.cpp, so this is its only entry point). `rgb` holds 3 bytes per
// pixel, rows of 3 * width bytes; width, height >= 1 and (3 width + 1) height must fit in
// an int (the caller checks). Returns false when stb fails (out of memory); never throws.
bool encode_png(const std::uint8_t* rgb, int width, int height, std::vector<unsigned char>& out) noexcept;

}  // namespace lsnif::image::internal
