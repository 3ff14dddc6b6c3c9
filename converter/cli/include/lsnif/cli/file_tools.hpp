// `lsnif inspect` and `lsnif validate`, as library functions so the tests run exactly
// the code the CLI runs. Both read files only through the C reader API of
// <lsnif/lsnif.h>, i.e. the way a renderer does.
#pragma once

#include <lsnif/lsnif.h>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace lsnif::cli {

struct Problem {
    std::string status;    // lsnif_status_string() of the failure, or "metadata"
    std::uint64_t offset;  // file offset or UINT64_MAX
    std::string message;
};

struct ValidationReport {
    std::string path;
    std::vector<Problem> problems;
    // Filled when the reader opened the file: "MAJOR.MINOR" and the grid encoding, with
    // each level's {scale, offset} for a quantized grid (FORMAT.md §6.4.1).
    std::string version;
    nlohmann::json grid;
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

// Everything `lsnif inspect --json` prints. On a file the reader rejects, the header
// and section table are still reported when they parse, plus the error.
nlohmann::json inspect_bytes(std::span<const std::uint8_t> bytes, const std::string& name);
std::string inspect_text(const nlohmann::json& report);

// Checks that the metadata's "model" and "object.box_*" agree with the binary
// descriptor (which is authoritative). Returns one message per disagreement.
// `ray_inputs` is lsnif_get_ray_inputs' value.
std::vector<std::string> metadata_consistency(const nlohmann::json& metadata, const lsnif_info& info,
                                              std::uint32_t ray_inputs);

}  // namespace lsnif::cli
