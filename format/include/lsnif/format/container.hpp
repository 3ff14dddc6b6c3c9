// C++ side of the .lsnif container: layout constants, the model descriptor, the
// in-memory model, and the reader/writer used by the trainer, converter and the C API.
//
// The byte layout is normative in schema/FORMAT.md; every constant here carries the
// section number of that document. Library code never throws across this interface:
// functions return Result/Error. (std::bad_alloc is caught and reported as
// LSNIF_ERR_OUT_OF_MEMORY.)
#pragma once

#include <lsnif/lsnif.h>
#include <lsnif/base/result.hpp>

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

namespace lsnif::format {

// ---- FORMAT.md §2-§4: container layout ----------------------------------------------

// \x8C L S N \r \n \x1A \n — high-bit first byte catches 7-bit transfers, CR LF catches
// line-ending conversion in either direction, ^Z stops DOS `type`.
inline constexpr std::array<std::uint8_t, 8> kMagic = {0x8C, 'L', 'S', 'N', 0x0D, 0x0A, 0x1A, 0x0A};
inline constexpr std::uint32_t kHeaderSize = 64;
inline constexpr std::uint32_t kEntrySize = 64;
inline constexpr std::uint64_t kAlignment = 64;
inline constexpr std::uint32_t kMaxSections = 64;
inline constexpr std::uint64_t kMaxSectionRawSize = std::uint64_t{1} << 30;  // 1 GiB
inline constexpr std::uint64_t kMaxFileSize = std::uint64_t{1} << 34;        // 16 GiB
inline constexpr std::uint64_t kMaxMetadataSize = std::uint64_t{1} << 20;    // 1 MiB
inline constexpr std::uint32_t kDescriptorSize = 256;

constexpr std::uint32_t make_tag(const char (&s)[5]) {
    return std::uint32_t(std::uint8_t(s[0])) | std::uint32_t(std::uint8_t(s[1])) << 8 |
           std::uint32_t(std::uint8_t(s[2])) << 16 | std::uint32_t(std::uint8_t(s[3])) << 24;
}
inline constexpr std::uint32_t kTagMeta = make_tag("META");   // JSON metadata
inline constexpr std::uint32_t kTagModel = make_tag("MODL");  // binary model descriptor
inline constexpr std::uint32_t kTagOccupancy = make_tag("OCCU");
inline constexpr std::uint32_t kTagGrid = make_tag("GRID");  // hash-grid tables (fp16 or u8, §6.4)
inline constexpr std::uint32_t kTagMlp = make_tag("MLPW");   // MLP weights, fp16

std::string tag_string(std::uint32_t tag);  // printable, non-ASCII bytes as \xNN

// ---- FORMAT.md §5: model descriptor limits ------------------------------------------
inline constexpr std::uint32_t kMaxGridResolution = 256;
inline constexpr std::uint32_t kMaxPoints = 64;
inline constexpr std::uint32_t kMaxFeatures = 8;
inline constexpr std::uint32_t kMinLog2TableSize = 4;
inline constexpr std::uint32_t kMaxLog2TableSize = 24;
inline constexpr std::uint32_t kMaxLevelResolution = 4096;
inline constexpr std::uint32_t kMaxHiddenWidth = 1024;
inline constexpr std::uint32_t kMaxMaterials = 4096;

// ---- FORMAT.md §2.4, §6.2: grid encodings and the version that introduced them --------
// MODL grid_encoding (descriptor offset 144). The values are LSNIF_GRID_* of lsnif.h.
enum class GridEncoding : std::uint32_t {
    fp16 = LSNIF_GRID_FP16,           // v1.0 layout: binary16 per feature
    u8_affine = LSNIF_GRID_U8_AFFINE  // v1.1: u8 per feature, per-level (scale, offset)
};
// The minor version a writer puts in the header: the lowest one that can express the
// model (FORMAT.md §2.4), so fp16 assets stay 1.0 files that 1.0 readers open.
inline constexpr std::uint16_t kMinorVersionFp16 = 0;
inline constexpr std::uint16_t kMinorVersionQuantized = 1;
// MODL ray_inputs (descriptor offset 148, since 1.2): a bit set of LSNIF_RAY_INPUT_* of
// lsnif.h; 0 = the MLP input is the H x L x F point features only.
inline constexpr std::uint32_t kRayInputDirection = LSNIF_RAY_INPUT_DIRECTION;
inline constexpr std::uint32_t kRayInputEntryOffsets = LSNIF_RAY_INPUT_ENTRY_OFFSETS;
inline constexpr std::uint32_t kRayInputsKnown = kRayInputDirection | kRayInputEntryOffsets;
inline constexpr std::uint16_t kMinorVersionRayInputs = 2;
// Inputs the direction adds after the point features (FORMAT.md §8).
inline constexpr std::uint32_t kDirectionInputs = 3;

// One output row of the network (FORMAT.md §6.5), by index: the visibility logit, the
// encoded distance (FORMAT.md §6.2 distance_encoding), the three components of the
// shading normal (not necessarily unit length), then material_count material logits.
// The one spelling of the layout for the reader's decode and the trainer's losses.
struct OutputLayout {
    static constexpr std::uint32_t visibility = 0;
    static constexpr std::uint32_t distance = 1;
    static constexpr std::uint32_t normal = 2;    // x, y, z at normal + 0, 1, 2
    static constexpr std::uint32_t material = 5;  // material m at material + m
};

// Hyperparameters of one LSNIF. The defaults are the original model (V = 32, H = 18, levels
// 64 and 128; the shipped preset differs: converter/convert/src/presets.cpp); a reader never uses
// them — every value is read from the file.
struct ModelDesc {
    std::uint32_t grid_resolution = 32;
    std::uint32_t max_points = 18;
    std::vector<std::uint32_t> level_resolution{64, 128};
    std::uint32_t features_per_level = 3;
    std::uint32_t log2_table_size = 17;
    std::array<std::uint32_t, 3> hash_primes{1u, 2654435761u, 805459861u};
    std::vector<std::uint32_t> hidden_width{128, 128};
    std::uint32_t material_count = 0;
    std::uint32_t activation = 0;  // ReLU
    std::uint32_t distance_encoding = LSNIF_DISTANCE_FIRST_ENTRY_DIAGONAL;
    std::array<float, 3> box_min{0.f, 0.f, 0.f};
    std::array<float, 3> box_max{1.f, 1.f, 1.f};
    // How GRID stores the features (FORMAT.md §6.4). fp16 keeps the file at version 1.0.
    GridEncoding grid_encoding = GridEncoding::fp16;
    // What else the MLP sees of the ray (kRayInput* bits, FORMAT.md §6.2, §8). 0 keeps the
    // file at version 1.0/1.1.
    std::uint32_t ray_inputs = 0;

    std::uint32_t level_count() const { return std::uint32_t(level_resolution.size()); }
    // Point features first (H x L x F, slot-major), then the direction (3), then the entry
    // offsets (H), each if its ray_inputs bit is set.
    std::uint32_t point_feature_width() const { return max_points * level_count() * features_per_level; }
    std::uint32_t direction_width() const { return ray_inputs & kRayInputDirection ? kDirectionInputs : 0; }
    std::uint32_t offset_width() const { return ray_inputs & kRayInputEntryOffsets ? max_points : 0; }
    std::uint32_t input_width() const { return point_feature_width() + direction_width() + offset_width(); }
    std::uint32_t output_count() const { return OutputLayout::material + material_count; }
    std::uint64_t table_size() const { return std::uint64_t{1} << log2_table_size; }
    // A level is dense when its (res+1)^3 lattice vertices fit in the table (FORMAT.md §6.4).
    bool level_dense(std::uint32_t level) const;
    std::uint64_t level_entries(std::uint32_t level) const;
    std::uint64_t voxel_count() const {
        return std::uint64_t(grid_resolution) * grid_resolution * grid_resolution;
    }
    std::uint32_t layer_count() const { return std::uint32_t(hidden_width.size()) + 1; }
    // Feature values of all levels: F * sum_l entries_l (whatever the encoding).
    std::uint64_t grid_value_count() const;
    // Raw size of the GRID section (FORMAT.md §6.4): 2 bytes per value for fp16;
    // 8 * L bytes of (scale, offset) pairs plus 1 byte per value for u8_affine.
    std::uint64_t grid_raw_size() const;
    // Header minor version the writer uses for this descriptor (FORMAT.md §2.4).
    std::uint16_t minor_version() const {
        if (ray_inputs != 0) return kMinorVersionRayInputs;
        return grid_encoding == GridEncoding::fp16 ? kMinorVersionFp16 : kMinorVersionQuantized;
    }
    // (out, in) of MLP layer k, hidden layers first, output layer last.
    std::pair<std::uint32_t, std::uint32_t> layer_shape(std::uint32_t layer) const;
    // Hash-table feature values + MLP weights and biases (per-level scale/offset pairs of
    // a quantized grid are not counted: the count does not depend on the encoding).
    std::uint64_t parameter_count() const;
};

struct Error {
    lsnif_status status = LSNIF_OK;
    std::uint64_t offset = UINT64_MAX;
    std::string message;
    explicit operator bool() const { return status != LSNIF_OK; }
};

template <class T>
using Result = base::Result<T, Error>;

// Checks ranges and internal consistency of a descriptor (FORMAT.md §5).
Error validate_desc(const ModelDesc& desc);

// Dequantization pair of one level of a u8_affine grid (FORMAT.md §6.4.1). Laid out as
// the two f32 the C API hands out for LSNIF_ARRAY_GRID_DEQUANT.
struct LevelAffine {
    float scale = 0.0f;  // >= 0 and finite; 0 makes the level constant (= offset)
    float offset = 0.0f;
};

// A complete model in memory: what the writer takes and the reader produces.
// Weight arrays are fp16 bit patterns in the layout of FORMAT.md §6. The grid is held in
// exactly one representation, the one desc.grid_encoding names; the other stays empty
// (validate_model checks it):
//   fp16:      grid[l] = entries_l * F binary16 patterns;
//   u8_affine: grid_u8[l] = entries_l * F bytes q, grid_affine[l] = (scale, offset), value
//              = dequantize_u8(q, scale, offset) of <lsnif/format/quantize.hpp>.
struct ModelData {
    ModelDesc desc;
    std::string metadata_json;
    std::vector<std::uint8_t> occupancy;              // ceil(V^3 / 8) bytes
    std::vector<std::vector<std::uint16_t>> grid;     // fp16: per level, entries * F
    std::vector<std::vector<std::uint8_t>> grid_u8;   // u8_affine: per level, entries * F
    std::vector<LevelAffine> grid_affine;             // u8_affine: per level
    std::vector<std::vector<std::uint16_t>> weights;  // per layer: out * in
    std::vector<std::vector<std::uint16_t>> biases;   // per layer: out
    // The version of the file read_model() read. serialize() ignores both and writes the
    // lowest version that can express the model (desc.minor_version(), FORMAT.md §2.4).
    std::uint16_t version_major = LSNIF_VERSION_MAJOR;
    std::uint16_t version_minor = kMinorVersionFp16;
};

// Allocates zeroed arrays of the right sizes for `desc` (occupancy all empty; a
// quantized grid gets zero bytes and (scale, offset) = (0, 0)).
Result<ModelData> make_empty_model(const ModelDesc& desc);

// Checks array sizes against the descriptor, that weights are finite and that unused
// occupancy bits are zero; for a quantized grid, the per-level checks of FORMAT.md §6.4.1
// (finite scale and offset, scale >= 0, finite dequantized 0 and 255) instead of the
// fp16 finiteness check.
Error validate_model(const ModelData& model);

// Extra section for writers that need to add optional data (and for tests that check
// that readers skip unknown optional sections / reject unknown required ones).
struct ExtraSection {
    std::uint32_t tag = 0;
    bool required = false;
    std::vector<std::uint8_t> payload;
};

struct WriteOptions {
    int zstd_level = 19;  // 0 = store uncompressed
    std::vector<ExtraSection> extra_sections;
};

// Serializes to the exact byte stream of FORMAT.md. Deterministic: the same model and
// options always give the same bytes.
Result<std::vector<std::uint8_t>> serialize(const ModelData& model, const WriteOptions& options = {});

// Writes `path` atomically: bytes go to a temporary file in the same directory, are
// flushed, then renamed over `path`. On failure no file (and no temporary) remains.
Error write_file(const std::string& path, const ModelData& model, const WriteOptions& options = {});
Error write_bytes_atomically(const std::string& path, std::span<const std::uint8_t> bytes);
// The same for text (JSON, XML, Ninja files): its bytes as they are.
Error write_text_atomically(const std::string& path, std::string_view text);

// ---- low level: for tools and tests that must build exact byte streams ----------------

// One section's uncompressed payload and flags, in table order.
struct RawSection {
    std::uint32_t tag = 0;
    std::uint32_t flags = LSNIF_SECTION_REQUIRED;
    std::vector<std::uint8_t> raw;
};

// The v1 sections of a model, as serialize() lays them out (no validation). The GRID
// layout follows desc.grid_encoding.
std::vector<RawSection> model_sections(const ModelData& model);
std::vector<std::uint8_t> encode_descriptor(const ModelDesc& desc);

// Assembles header, table and payloads exactly as serialize() does, without checking
// the sections' content. zstd_level 0 stores every section uncompressed. The version
// written is major.minor (default 1.0: pass kMinorVersionQuantized for quantized grids).
Result<std::vector<std::uint8_t>> assemble(const std::vector<RawSection>& sections, int zstd_level,
                                           std::uint16_t major = LSNIF_VERSION_MAJOR,
                                           std::uint16_t minor = kMinorVersionFp16);

// Full verification and decode (what lsnif_open_memory does).
Result<ModelData> read_model(std::span<const std::uint8_t> bytes);
Result<std::vector<std::uint8_t>> read_file_bytes(const std::string& path);

// The container structure without building a model (what lsnif_scan_memory does).
struct ScanResult {
    lsnif_header_info header{};
    std::vector<lsnif_section_info> sections;
    Error first_payload_error;  // checksum/decompression problems, after the whole scan
};
Result<ScanResult> scan(std::span<const std::uint8_t> bytes);

// CRC-32C (Castagnoli, reflected polynomial 0x82F63B78), as in iSCSI / RFC 3720.
std::uint32_t crc32c(const void* data, std::size_t size, std::uint32_t crc = 0);

}  // namespace lsnif::format
