// libFuzzer target for the runtime reader: every entry point a renderer calls on
// untrusted bytes. Built with clang by scripts/fuzz; built with GCC and
// replay_main.cpp as a CTest that replays the committed corpus.
#include <lsnif/lsnif.h>

#include <cstddef>
#include <cstdint>

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
        lsnif_close(model);
    }
    return 0;
}
