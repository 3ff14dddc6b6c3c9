// The names the metadata (schema/lsnif-metadata.schema.json, "model") and the manifest give
// three enumerations of the binary descriptor (lsnif.h): the one spelling for the writer
// (`lsnif convert`) and for the readers that check it against the descriptor (`lsnif
// validate`, `lsnif inspect`).
#pragma once

#include <cstdint>

namespace lsnif::converter {

// LSNIF_DISTANCE_SEGMENT is "segment", any other value "first_entry_diagonal".
const char* distance_encoding_name(std::uint32_t distance_encoding);
// "fp16", "u8_affine", or "unknown" for an encoding this reader does not define.
const char* grid_encoding_name(std::uint32_t grid_encoding);
// The LSNIF_RAY_INPUT_* bits: "none", "direction", "entry_offsets", "direction+entry_offsets",
// or "unknown".
const char* ray_inputs_name(std::uint32_t ray_inputs);

}  // namespace lsnif::converter
