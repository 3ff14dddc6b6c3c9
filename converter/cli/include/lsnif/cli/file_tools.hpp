// `lsnif inspect` and `lsnif validate`, as library functions so the tests run exactly
// the code the CLI runs. Both read files only through the C reader API of
// <lsnif/lsnif.h>, i.e. the way a renderer does.
#pragma once

#include <lsnif/lsnif.h>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace lsnif::cli {

struct Problem {
    std::string status;    // lsnif_status_string() of the failure, or "metadata"
    std::uint64_t offset;  // file offset or UINT64_MAX
    std::string message;
};

// An opened asset's grid encoding and, for a quantized grid, each level's dequantization
// pair (FORMAT.md §6.4.1) as the C API hands it to a GPU uploader.
struct GridDequant {
    float scale = 0, offset = 0;
};
struct GridInfo {
    std::string encoding;             // grid_encoding_name()
    bool quantized = false;           // u8_affine: `levels` is meaningful
    std::vector<GridDequant> levels;  // one per level the reader handed out
};
nlohmann::json grid_info_json(const GridInfo& grid);

struct ValidationReport {
    std::string path;
    std::vector<Problem> problems;
    // Filled when the reader opened the file: "MAJOR.MINOR" and the grid.
    std::string version;
    std::optional<GridInfo> grid;
    bool valid() const { return problems.empty(); }
    nlohmann::json to_json() const;
    // One line per problem: "PATH: error: MESSAGE", or "PATH: ok" (for a quantized grid
    // followed by "  format 1.1, grid u8_affine: level 0 scale S offset O; ...").
    std::string to_text() const;
};

// Structure, checksums, model consistency and finiteness (the reader's checks), then
// metadata against schema/lsnif-metadata.schema.json and against the binary descriptor.
ValidationReport validate_bytes(std::span<const std::uint8_t> bytes, const std::string& name);
ValidationReport validate_file(const std::string& path);

// What a renderer holds with an asset open: on this CPU, in the arithmetic lsnif_open chose,
// and with the fp32 network, which every CPU runs and which holds the least (the figure the
// conversion's rules count); beside the file. Bytes.
struct InspectMemory {
    std::uint64_t file_bytes = 0, resident_bytes = 0, resident_bytes_fp32 = 0;
    std::string arithmetic;  // lsnif_arithmetic_string() of the chosen arithmetic
};
// The opened model as the reader describes it.
struct InspectModel {
    lsnif_info info{};
    std::uint32_t ray_inputs = 0;  // lsnif_get_ray_inputs() bits
    GridInfo grid;
};
// Everything `lsnif inspect` reports. On a file the reader rejects, the header and section
// table are still reported when they parse, plus the error; model, memory and metadata
// only for a file the reader opened.
struct InspectReport {
    std::string path;
    std::uint64_t file_size = 0;               // bytes given
    std::optional<lsnif_header_info> header;   // when the section table parsed
    std::vector<lsnif_section_info> sections;  // the table's entries, in file order
    std::optional<Problem> error;              // why the reader rejected the file
    std::optional<InspectModel> model;
    std::optional<InspectMemory> memory;
    std::optional<nlohmann::json> metadata;  // the metadata section, when it parses as JSON
    std::string metadata_text;               // the metadata section as stored
    bool ok() const { return !error; }
};
InspectReport inspect_bytes(std::span<const std::uint8_t> bytes, const std::string& name);
nlohmann::json inspect_json(const InspectReport& report);  // `lsnif inspect --json`
std::string inspect_text(const InspectReport& report);     // `lsnif inspect`

// Checks that the metadata's "model" and "object.box_*" agree with the binary
// descriptor (which is authoritative). Returns one message per disagreement.
// `ray_inputs` is lsnif_get_ray_inputs' value.
std::vector<std::string> metadata_consistency(const nlohmann::json& metadata, const lsnif_info& info,
                                              std::uint32_t ray_inputs);

}  // namespace lsnif::cli
