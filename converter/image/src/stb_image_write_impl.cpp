// The one translation unit that compiles stb_image_write's implementation (Debian's
// libstb-dev ships the header). STB_IMAGE_WRITE_STATIC gives every stb function internal
// linkage, so this copy can never collide with another stb in the same program (tinygltf,
// a renderer embedding the converter); encode_png() below is the only way in.
// STBI_WRITE_NO_STDIO removes stb's own file output: image.cpp writes the bytes itself so
// it can check every write and publish the file atomically.
#include "internal.hpp"

#include <new>

#define STB_IMAGE_WRITE_STATIC
#define STB_IMAGE_WRITE_IMPLEMENTATION
#define STBI_WRITE_NO_STDIO
#include <stb/stb_image_write.h>

namespace lsnif::image::internal {
namespace {

struct Sink {
    std::vector<unsigned char>* out;
    bool failed = false;
};

// stb hands over the finished PNG (in one call for PNG); appending may run out of memory,
// which must not unwind through stb's C code (it would leak stb's buffer).
void append(void* context, void* data, int size) {
    auto* sink = static_cast<Sink*>(context);
    if (sink->failed || size <= 0) return;
    const auto* bytes = static_cast<const unsigned char*>(data);
    try {
        sink->out->insert(sink->out->end(), bytes, bytes + size);
    } catch (const std::bad_alloc&) {
        sink->failed = true;
    }
}

}  // namespace

bool encode_png(const std::uint8_t* rgb, int width, int height, std::vector<unsigned char>& out) noexcept {
    out.clear();
    Sink sink{&out};
    const int ok = stbi_write_png_to_func(append, &sink, width, height, 3, rgb, 3 * width);
    return ok != 0 && !sink.failed && !out.empty();
}

}  // namespace lsnif::image::internal
