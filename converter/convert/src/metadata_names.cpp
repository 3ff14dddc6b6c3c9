// The metadata's names of the descriptor's enumerations (metadata_names.hpp).
#include <lsnif/lsnif.h>
#include <lsnif/converter/metadata_names.hpp>

namespace lsnif::converter {

const char* distance_encoding_name(std::uint32_t e) {
    return e == LSNIF_DISTANCE_SEGMENT ? "segment" : "first_entry_diagonal";
}

const char* grid_encoding_name(std::uint32_t e) {
    return e == LSNIF_GRID_U8_AFFINE ? "u8_affine" : e == LSNIF_GRID_FP16 ? "fp16" : "unknown";
}

const char* ray_inputs_name(std::uint32_t bits) {
    switch (bits) {
        case 0: return "none";
        case LSNIF_RAY_INPUT_DIRECTION: return "direction";
        case LSNIF_RAY_INPUT_ENTRY_OFFSETS: return "entry_offsets";
        case LSNIF_RAY_INPUT_DIRECTION | LSNIF_RAY_INPUT_ENTRY_OFFSETS: return "direction+entry_offsets";
        default: return "unknown";
    }
}

}  // namespace lsnif::converter
