// libFuzzer target for the runtime reader: every entry point a renderer calls on
// untrusted bytes, tracing included. Built with clang by scripts/fuzz; built with GCC and
// replay_main.cpp as a CTest that replays the committed corpus.
#include <lsnif/lsnif.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <initializer_list>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    lsnif_header_info header;
    lsnif_section_info sections[64];
    std::uint32_t count = 0;
    lsnif_error err;
    lsnif_scan_memory(data, size, &header, sections, 64, &count, &err);
    lsnif_model* model = nullptr;
    if (lsnif_open_memory(data, size, &model, &err) == LSNIF_OK) {
        lsnif_info info;
        lsnif_get_info(model, &info);
        std::size_t len = 0;
        lsnif_metadata(model, &len);
        // Touch every array the reader hands out: must all be in bounds.
        volatile std::uint8_t sink = 0;
        for (std::uint32_t k = 0; k < lsnif_layer_count(model); ++k) {
            lsnif_array a;
            if (lsnif_get_array(model, LSNIF_ARRAY_LAYER_WEIGHTS, k, &a) == LSNIF_OK && a.bytes)
                sink = sink + static_cast<const std::uint8_t*>(a.data)[a.bytes - 1];
        }
        for (std::uint32_t l = 0; l < info.level_count; ++l) {
            lsnif_array a;
            if (lsnif_get_array(model, LSNIF_ARRAY_GRID_LEVEL, l, &a) == LSNIF_OK && a.bytes)
                sink = sink + static_cast<const std::uint8_t*>(a.data)[a.bytes - 1];
            // Quantized grids (1.1) also hand out their {scale, offset} pair.
            if (lsnif_get_array(model, LSNIF_ARRAY_GRID_DEQUANT, l, &a) == LSNIF_OK && a.bytes)
                sink = sink + static_cast<const std::uint8_t*>(a.data)[a.bytes - 1];
        }
        (void)sink;
        // A file that opens must be safe to trace: rays through its box (corner to corner,
        // along the axes, from outside, a zero direction, a NaN origin), in object space and
        // through an instance, with every arithmetic.
        lsnif_ray rays[16];
        const float* lo = info.box_min;
        const float* hi = info.box_max;
        for (int k = 0; k < 8; ++k) {
            lsnif_ray& r = rays[k];
            for (int a = 0; a < 3; ++a) {
                const bool high = (k >> a) & 1;
                r.org[a] = high ? hi[a] : lo[a];
                r.dir[a] = (high ? lo[a] : hi[a]) - r.org[a];
            }
            r.tmin = 0.0f;
            r.tmax = k % 2 ? 1.0f : INFINITY;
        }
        for (int k = 8; k < 14; ++k) {
            lsnif_ray& r = rays[k];
            const int axis = (k - 8) % 3;
            for (int a = 0; a < 3; ++a) {
                r.org[a] = 0.5f * (lo[a] + hi[a]);
                r.dir[a] = 0.0f;
            }
            r.org[axis] = k < 11 ? lo[axis] - 1.0f : hi[axis] + 1.0f;
            r.dir[axis] = k < 11 ? 1.0f : -1.0f;
            r.tmin = 0.0f;
            r.tmax = INFINITY;
        }
        rays[14] = {{lo[0], lo[1], lo[2]}, 0.0f, {0.0f, 0.0f, 0.0f}, INFINITY};
        rays[15] = {{NAN, 0.0f, 0.0f}, 0.0f, {1.0f, 0.0f, 0.0f}, INFINITY};
        lsnif_hit hits[16];
        std::uint8_t occluded[16];
        const float placed[12] = {2, 0, 0, 1, 0, 2, 0, -1, 0, 0, 2, 0.5f};
        for (const lsnif_arithmetic a :
             {LSNIF_ARITHMETIC_FP32, LSNIF_ARITHMETIC_BF16, LSNIF_ARITHMETIC_INT8, LSNIF_ARITHMETIC_AUTO}) {
            lsnif_arithmetic used;
            lsnif_set_arithmetic(model, a, &used);
            lsnif_intersect(model, rays, 16, hits);
            lsnif_occluded(model, rays, 16, occluded);
            lsnif_intersect_instance(model, placed, rays, 16, hits);
            lsnif_occluded_instance(model, placed, rays, 16, occluded);
        }
        lsnif_close(model);
    }
    return 0;
}
