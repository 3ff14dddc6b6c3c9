// Reader and writer of the .lsnif container (schema/FORMAT.md). Every check below
// quotes the FORMAT.md section that requires it. All size arithmetic is done in 64 bits
// after bounding each operand, so no sum or product can wrap.
#include <lsnif/base/text.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>

#include "bytes.hpp"

#include <zstd.h>

#include <algorithm>
#include <cerrno>
#include <cinttypes>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <new>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

namespace lsnif::format {

using namespace detail;

namespace {

// The first four bytes of a Zstandard frame (RFC 8878 §3.1.1), little-endian.
constexpr std::uint32_t kZstdFrameMagic = 0xFD2FB528;

Error make_error(lsnif_status status, std::uint64_t offset, const char* fmt, ...)
    __attribute__((format(printf, 3, 4)));

Error make_error(lsnif_status status, std::uint64_t offset, const char* fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    std::string message = base::vprinted(fmt, ap);
    va_end(ap);
    return Error{status, offset, std::move(message)};
}

// FORMAT.md §3: CRC-32C, reflected, init ~0, final xor ~0.
struct Crc32cTable {
    std::uint32_t t[8][256];
    Crc32cTable() {
        for (std::uint32_t i = 0; i < 256; ++i) {
            std::uint32_t c = i;
            for (int k = 0; k < 8; ++k) c = (c >> 1) ^ (0x82F63B78u & (0u - (c & 1u)));
            t[0][i] = c;
        }
        for (std::uint32_t i = 0; i < 256; ++i)
            for (int s = 1; s < 8; ++s) t[s][i] = (t[s - 1][i] >> 8) ^ t[0][t[s - 1][i] & 0xFFu];
    }
};
const Crc32cTable& crc_table() {
    static const Crc32cTable table;
    return table;
}

// FORMAT.md §4.2: tags are four printable ASCII characters.
bool tag_printable(std::uint32_t tag) {
    for (int i = 0; i < 4; ++i) {
        const unsigned c = (tag >> (8 * i)) & 0xFFu;
        if (c < 0x21 || c > 0x7E) return false;
    }
    return true;
}

bool is_known_tag(std::uint32_t tag) {
    return tag == kTagMeta || tag == kTagModel || tag == kTagOccupancy || tag == kTagGrid || tag == kTagMlp;
}

bool valid_utf8(const std::uint8_t* s, std::size_t n) {
    std::size_t i = 0;
    while (i < n) {
        const std::uint8_t c = s[i];
        if (c == 0) return false;
        if (c < 0x80) {
            ++i;
            continue;
        }
        std::size_t len;
        std::uint32_t cp;
        if ((c & 0xE0) == 0xC0)
            len = 2, cp = c & 0x1F;
        else if ((c & 0xF0) == 0xE0)
            len = 3, cp = c & 0x0F;
        else if ((c & 0xF8) == 0xF0)
            len = 4, cp = c & 0x07;
        else
            return false;
        if (n - i < len) return false;
        for (std::size_t k = 1; k < len; ++k) {
            if ((s[i + k] & 0xC0) != 0x80) return false;
            cp = (cp << 6) | (s[i + k] & 0x3F);
        }
        if ((len == 2 && cp < 0x80) || (len == 3 && cp < 0x800) || (len == 4 && cp < 0x10000) ||
            cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF))
            return false;
        i += len;
    }
    return true;
}

std::uint64_t align_up(std::uint64_t v) {
    return (v + kAlignment - 1) & ~(kAlignment - 1);
}

// ---- FORMAT.md §5: descriptor encoding ----------------------------------------------

std::vector<std::uint8_t> encode_desc(const ModelDesc& d) {
    std::vector<std::uint8_t> b(kDescriptorSize, 0);
    std::uint8_t* p = b.data();
    store_u32(p + 0, kDescriptorSize);
    store_u32(p + 4, d.grid_resolution);
    store_u32(p + 8, d.max_points);
    store_u32(p + 12, d.level_count());
    store_u32(p + 16, d.features_per_level);
    store_u32(p + 20, d.log2_table_size);
    for (std::uint32_t l = 0; l < d.level_count() && l < LSNIF_MAX_LEVELS; ++l)
        store_u32(p + 24 + 4 * l, d.level_resolution[l]);
    store_u32(p + 56, std::uint32_t(d.hidden_width.size()));
    for (std::size_t k = 0; k < d.hidden_width.size() && k < LSNIF_MAX_HIDDEN_LAYERS; ++k)
        store_u32(p + 60 + 4 * k, d.hidden_width[k]);
    store_u32(p + 92, d.output_count());
    store_u32(p + 96, d.material_count);
    store_u32(p + 100, d.activation);
    store_u32(p + 104, d.distance_encoding);
    for (int i = 0; i < 3; ++i) store_u32(p + 108 + 4 * i, d.hash_primes[i]);
    for (int i = 0; i < 3; ++i) store_f32(p + 120 + 4 * i, d.box_min[i]);
    for (int i = 0; i < 3; ++i) store_f32(p + 132 + 4 * i, d.box_max[i]);
    // 0 for fp16, so an fp16 descriptor is byte-identical to a 1.0 one.
    store_u32(p + 144, std::uint32_t(d.grid_encoding));
    // 0 without ray inputs: such a descriptor is byte-identical to a 1.1 one.
    store_u32(p + 148, d.ray_inputs);
    return b;
}

// FORMAT.md §7.2 E4.2-E4.5: a count in 1..max stored at `count_at`, then `max` u32 slots
// at `slots_at` of which the first `count` are read into `out` and the rest must be zero.
// The names are the descriptor fields' (§6.2), quoted in the error.
Error decode_slots(const std::uint8_t* p, std::uint64_t file_offset, std::size_t count_at,
                   std::size_t slots_at, std::uint32_t max, const char* count_name, const char* slot_name,
                   std::vector<std::uint32_t>& out) {
    const std::uint32_t count = load_u32(p + count_at);
    if (count < 1 || count > max)
        return make_error(LSNIF_ERR_MODEL, file_offset, "MODL section: %s %u outside 1..%u", count_name,
                          count, max);
    out.assign(count, 0);
    for (std::uint32_t k = 0; k < max; ++k) {
        const std::uint32_t v = load_u32(p + slots_at + 4 * k);
        if (k < count)
            out[k] = v;
        else if (v != 0)
            return make_error(LSNIF_ERR_RESERVED, file_offset,
                              "MODL section: %s[%u] is %u but %s is %u "
                              "(unused slots must be zero)",
                              slot_name, k, v, count_name, count);
    }
    return {};
}

// Bytes 144..255 of a descriptor in a file of header minor version `minor`: 1.0 reserves
// them all, 1.1 defines grid_encoding (144..147), 1.2 also ray_inputs (148..151); what is
// not defined must be zero (FORMAT.md §6.2, §7.2 E4.6/E4.6a).
Error decode_desc_tail(const std::uint8_t* p, std::uint64_t file_offset, std::uint16_t minor, ModelDesc& d) {
    if (minor < kMinorVersionQuantized) {
        // 1.0: grid_encoding does not exist yet; the bytes are reserved as they always were.
        if (!all_zero(p + 144, kDescriptorSize - 144))
            return make_error(LSNIF_ERR_RESERVED, file_offset,
                              "MODL section: reserved bytes 144..255 are not zero");
        return {};
    }
    const std::uint32_t reserved_from = minor < kMinorVersionRayInputs ? 148 : 152;
    if (!all_zero(p + reserved_from, kDescriptorSize - reserved_from))
        return make_error(LSNIF_ERR_RESERVED, file_offset,
                          "MODL section: reserved bytes %u..255 are not zero", reserved_from);
    const std::uint32_t enc = load_u32(p + 144);
    if (enc > LSNIF_GRID_U8_AFFINE)
        return make_error(LSNIF_ERR_MODEL, file_offset,
                          "MODL section: grid_encoding %u unknown (0 = fp16, 1 = u8 affine)", enc);
    d.grid_encoding = GridEncoding(enc);
    if (minor >= kMinorVersionRayInputs) {
        const std::uint32_t inputs = load_u32(p + 148);
        if (inputs & ~kRayInputsKnown)
            return make_error(
                LSNIF_ERR_MODEL, file_offset,
                "MODL section: ray_inputs 0x%x has unknown bits (1 = direction, 2 = entry offsets)", inputs);
        d.ray_inputs = inputs;
    }
    return {};
}

// `minor` is the file's header minor version: it decides what bytes 144..255 may hold
// (FORMAT.md §6.2, §7.2 E4.6/E4.6a).
Result<ModelDesc> decode_desc(const std::vector<std::uint8_t>& b, std::uint64_t file_offset,
                              std::uint16_t minor) {
    if (b.size() != kDescriptorSize)
        return make_error(LSNIF_ERR_MODEL, file_offset, "MODL section: size %zu, expected exactly %u bytes",
                          b.size(), kDescriptorSize);
    const std::uint8_t* p = b.data();
    if (load_u32(p) != kDescriptorSize)
        return make_error(LSNIF_ERR_MODEL, file_offset,
                          "MODL section: descriptor_size field is %u, expected %u", load_u32(p),
                          kDescriptorSize);
    ModelDesc d;
    d.grid_resolution = load_u32(p + 4);
    d.max_points = load_u32(p + 8);
    d.features_per_level = load_u32(p + 16);
    d.log2_table_size = load_u32(p + 20);
    if (Error e = decode_slots(p, file_offset, 12, 24, LSNIF_MAX_LEVELS, "level_count", "level_resolution",
                               d.level_resolution))
        return e;
    if (Error e = decode_slots(p, file_offset, 56, 60, LSNIF_MAX_HIDDEN_LAYERS, "hidden_layer_count",
                               "hidden_width", d.hidden_width))
        return e;
    const std::uint32_t outputs = load_u32(p + 92);
    d.material_count = load_u32(p + 96);
    d.activation = load_u32(p + 100);
    d.distance_encoding = load_u32(p + 104);
    for (int i = 0; i < 3; ++i) d.hash_primes[i] = load_u32(p + 108 + 4 * i);
    for (int i = 0; i < 3; ++i) d.box_min[i] = load_f32(p + 120 + 4 * i);
    for (int i = 0; i < 3; ++i) d.box_max[i] = load_f32(p + 132 + 4 * i);
    if (Error e = decode_desc_tail(p, file_offset, minor, d)) return e;
    if (Error e = validate_desc(d)) {
        e.offset = file_offset;
        e.message = "MODL section: " + e.message;
        return e;
    }
    if (outputs != d.output_count())
        return make_error(LSNIF_ERR_MODEL, file_offset,
                          "MODL section: output_count %u, expected 5 + material_count = %u", outputs,
                          d.output_count());
    return d;
}

// ---- FORMAT.md §4: header and section table -----------------------------------------

struct Entry {
    std::uint32_t tag, flags, compression;
    std::uint64_t offset, stored_size, raw_size;
    std::uint32_t stored_crc, raw_crc;
    std::uint64_t entry_offset;  // where the entry itself sits in the file
};

struct Structure {
    lsnif_header_info header{};
    std::vector<Entry> entries;
};

Error check_magic(std::span<const std::uint8_t> b) {
    const std::size_t n = std::min<std::size_t>(b.size(), kMagic.size());
    if (std::equal(b.begin(), b.begin() + n, kMagic.begin())) {
        if (b.size() < kMagic.size())
            return make_error(LSNIF_ERR_TRUNCATED, 0, "file is %zu bytes, shorter than the 8-byte signature",
                              b.size());
        return {};
    }
    // Same "LSN" core but damaged framing bytes: the file went through a text-mode or
    // 7-bit channel (FORMAT.md §4.1 explains each byte).
    if (b.size() >= 4 && b[1] == 'L' && b[2] == 'S' && b[3] == 'N') {
        const char* why = "signature bytes altered";
        if (b[0] == 0x0C)
            why = "high bit of byte 0 stripped (7-bit transfer)";
        else if (b.size() >= 6 && b[4] == 0x0A)
            why = "CR LF converted to LF (text-mode transfer)";
        else if (b.size() >= 6 && b[4] == 0x0D && b[5] == 0x0D)
            why = "LF converted to CR LF (text-mode transfer)";
        else if (b.size() >= 8 && b[4] == 0x0D && b[5] == 0x0A && b[6] == 0x1A && b[7] == 0x0D)
            why = "LF converted to CR LF (text-mode transfer)";
        return make_error(LSNIF_ERR_TRANSFER_DAMAGE, 0,
                          "signature damaged in transfer: %s; copy the file in binary mode", why);
    }
    return make_error(LSNIF_ERR_NOT_LSNIF, 0, "not an .lsnif file (signature mismatch)");
}

// The stages of parse_structure, in the order FORMAT.md's checks must run (the first
// failing rule decides the error a file gets; tests/golden pins every one). Each returns an
// Error whose status is LSNIF_OK when the rule holds.

// Bytes 8..11: the version. Runs first after the signature: FORMAT.md §2 freezes bytes
// 0..11 across every version, so nothing whose layout a future major version could change
// is read before it. Requires b.size() >= 12.
Error check_version(std::span<const std::uint8_t> b) {
    const std::uint8_t* h = b.data();
    const std::uint16_t major = load_u16(h + 8), minor = load_u16(h + 10);
    if (major > LSNIF_VERSION_MAJOR)
        return make_error(LSNIF_ERR_VERSION_NEWER, 8,
                          "format version %u.%u was written by a newer lsnif (this reader reads "
                          "%u.0 to %u.%u); upgrade lsnif",
                          major, minor, LSNIF_VERSION_MAJOR, LSNIF_VERSION_MAJOR, LSNIF_VERSION_MINOR);
    if (major < LSNIF_VERSION_MAJOR)
        return make_error(LSNIF_ERR_VERSION_OLDER, 8,
                          "format version %u.%u is older than this reader supports (%u.x); "
                          "re-convert the asset",
                          major, minor, LSNIF_VERSION_MAJOR);
    if (minor > LSNIF_VERSION_MINOR)
        return make_error(LSNIF_ERR_VERSION_NEWER, 10,
                          "format version %u.%u was written by a newer lsnif (this reader reads "
                          "up to %u.%u); upgrade lsnif",
                          major, minor, LSNIF_VERSION_MAJOR, LSNIF_VERSION_MINOR);
    return {};
}

// The 64-byte header (checksum, sizes, reserved fields) into s.header, and the declared
// file size against the bytes present. `table_crc` receives the header's checksum of the
// section table, which check_section_table verifies.
Error parse_header(std::span<const std::uint8_t> b, Structure& s, std::uint32_t& table_crc) {
    const std::uint8_t* h = b.data();
    const std::uint16_t major = load_u16(h + 8), minor = load_u16(h + 10);
    if (b.size() < kHeaderSize)
        return make_error(LSNIF_ERR_TRUNCATED, b.size(), "file is %zu bytes, shorter than the 64-byte header",
                          b.size());
    const std::uint32_t header_crc = load_u32(h + 60);
    const std::uint32_t actual_header_crc = crc32c(h, 60);
    if (header_crc != actual_header_crc)
        return make_error(LSNIF_ERR_CHECKSUM, 60,
                          "header checksum mismatch (stored %08" PRIx32 ", computed %08" PRIx32 ")",
                          header_crc, actual_header_crc);
    const std::uint32_t header_size = load_u32(h + 12);
    if (header_size != kHeaderSize)
        return make_error(LSNIF_ERR_LAYOUT, 12, "header_size is %u, expected %u", header_size, kHeaderSize);
    s.header.version_major = major;
    s.header.version_minor = minor;
    s.header.file_size = load_u64(h + 16);
    s.header.table_offset = load_u64(h + 24);
    s.header.section_count = load_u32(h + 32);
    const std::uint32_t entry_size = load_u32(h + 36);
    table_crc = load_u32(h + 40);
    const std::uint32_t flags = load_u32(h + 44);
    if (flags != 0)
        return make_error(LSNIF_ERR_RESERVED, 44, "header flags are %08" PRIx32 ", must be zero in 1.x",
                          flags);
    if (!all_zero(h + 48, 12))
        return make_error(LSNIF_ERR_RESERVED, 48, "header reserved bytes 48..59 are not zero");
    if (entry_size != kEntrySize)
        return make_error(LSNIF_ERR_LAYOUT, 36, "section entry size is %u, expected %u", entry_size,
                          kEntrySize);
    if (s.header.file_size > kMaxFileSize)
        return make_error(LSNIF_ERR_LIMIT, 16,
                          "declared file size %" PRIu64 " exceeds the limit of %" PRIu64 " bytes",
                          s.header.file_size, kMaxFileSize);
    if (b.size() < s.header.file_size)
        return make_error(LSNIF_ERR_TRUNCATED, b.size(),
                          "file is truncated: %zu bytes present, header declares %" PRIu64, b.size(),
                          s.header.file_size);
    if (b.size() > s.header.file_size)
        return make_error(LSNIF_ERR_LAYOUT, s.header.file_size,
                          "%" PRIu64 " unexpected bytes after the declared end of file (%" PRIu64 " bytes)",
                          std::uint64_t(b.size()) - s.header.file_size, s.header.file_size);
    return {};
}

// The section table's place in the file and its checksum.
Error check_section_table(std::span<const std::uint8_t> b, const Structure& s, std::uint32_t table_crc) {
    const std::uint8_t* h = b.data();
    const std::uint32_t count = s.header.section_count;
    if (count < 1 || count > kMaxSections)
        return make_error(LSNIF_ERR_LIMIT, 32, "section count %u outside 1..%u", count, kMaxSections);
    const std::uint64_t table_offset = s.header.table_offset;
    const std::uint64_t table_bytes = std::uint64_t(count) * kEntrySize;
    if (table_offset < kHeaderSize || table_offset % kAlignment != 0 || table_offset > s.header.file_size ||
        s.header.file_size - table_offset < table_bytes)
        return make_error(LSNIF_ERR_LAYOUT, 24,
                          "section table (offset %" PRIu64 ", %" PRIu64
                          " bytes) is misaligned or outside the file (%" PRIu64 " bytes)",
                          table_offset, table_bytes, s.header.file_size);
    const std::uint32_t actual_table_crc = crc32c(h + table_offset, table_bytes);
    if (table_crc != actual_table_crc)
        return make_error(LSNIF_ERR_CHECKSUM, table_offset,
                          "section table checksum mismatch (stored %08" PRIx32 ", computed %08" PRIx32 ")",
                          table_crc, actual_table_crc);
    return {};
}

// Entry i of the section table (at file offset eo) into `en`, checked on its own and
// against the entries before it (s.entries).
Error parse_entry(std::span<const std::uint8_t> b, std::uint32_t i, std::uint64_t eo, const Structure& s,
                  Entry& en) {
    const std::uint8_t* e = b.data() + eo;
    en = Entry{load_u32(e),      load_u32(e + 4),  load_u32(e + 8),
               load_u64(e + 16), load_u64(e + 24), load_u64(e + 32),
               load_u32(e + 40), load_u32(e + 44), eo};
    const std::string tag = tag_string(en.tag);
    if (!tag_printable(en.tag))
        return make_error(LSNIF_ERR_LAYOUT, eo, "section %u: tag '%s' is not four printable ASCII characters",
                          i, tag.c_str());
    for (const Entry& prev : s.entries)
        if (prev.tag == en.tag)
            return make_error(LSNIF_ERR_LAYOUT, eo, "section %u: duplicate tag '%s'", i, tag.c_str());
    if (en.flags & ~std::uint32_t{LSNIF_SECTION_REQUIRED})
        return make_error(LSNIF_ERR_RESERVED, eo + 4, "section %u ('%s'): unknown flag bits %08" PRIx32, i,
                          tag.c_str(), en.flags);
    if (load_u32(e + 12) != 0 || !all_zero(e + 48, 16))
        return make_error(LSNIF_ERR_RESERVED, eo, "section %u ('%s'): reserved entry fields are not zero", i,
                          tag.c_str());
    if (en.compression > LSNIF_COMPRESSION_ZSTD)
        return make_error(LSNIF_ERR_LAYOUT, eo + 8, "section %u ('%s'): unknown compression method %u", i,
                          tag.c_str(), en.compression);
    if (en.raw_size > kMaxSectionRawSize)
        return make_error(LSNIF_ERR_LIMIT, eo + 32,
                          "section %u ('%s'): uncompressed size %" PRIu64 " exceeds the limit of %" PRIu64
                          " bytes",
                          i, tag.c_str(), en.raw_size, kMaxSectionRawSize);
    if (en.compression == LSNIF_COMPRESSION_NONE && en.stored_size != en.raw_size)
        return make_error(LSNIF_ERR_LAYOUT, eo + 24,
                          "section %u ('%s'): uncompressed section has stored size %" PRIu64
                          " but raw size %" PRIu64,
                          i, tag.c_str(), en.stored_size, en.raw_size);
    if (en.compression == LSNIF_COMPRESSION_ZSTD &&
        (en.stored_size == 0 || en.stored_size > ZSTD_compressBound(en.raw_size)))
        return make_error(LSNIF_ERR_LIMIT, eo + 24,
                          "section %u ('%s'): compressed size %" PRIu64 " impossible for raw size %" PRIu64,
                          i, tag.c_str(), en.stored_size, en.raw_size);
    if (en.offset % kAlignment != 0 || en.offset > s.header.file_size ||
        s.header.file_size - en.offset < en.stored_size)
        return make_error(LSNIF_ERR_LAYOUT, eo + 16,
                          "section %u ('%s'): payload (offset %" PRIu64 ", %" PRIu64
                          " bytes) is misaligned or outside the file (%" PRIu64 " bytes)",
                          i, tag.c_str(), en.offset, en.stored_size, s.header.file_size);
    if (!is_known_tag(en.tag) && (en.flags & LSNIF_SECTION_REQUIRED))
        return make_error(LSNIF_ERR_UNKNOWN_REQUIRED, eo,
                          "section %u ('%s') is marked required but unknown to this reader "
                          "(format %u.%u); upgrade lsnif",
                          i, tag.c_str(), LSNIF_VERSION_MAJOR, LSNIF_VERSION_MINOR);
    return {};
}

// FORMAT.md §4.3: the header, the table and the payloads (`regions`, [begin, end)) never
// overlap, and every byte outside them is zero padding.
Error check_regions(std::span<const std::uint8_t> b,
                    std::vector<std::pair<std::uint64_t, std::uint64_t>> regions, std::uint64_t file_size) {
    const std::uint8_t* h = b.data();
    std::sort(regions.begin(), regions.end());
    std::uint64_t cursor = 0;
    for (const auto& [begin, end] : regions) {
        if (begin < cursor)
            return make_error(LSNIF_ERR_LAYOUT, begin,
                              "region at offset %" PRIu64 " overlaps the previous one (ends at %" PRIu64 ")",
                              begin, cursor);
        if (!all_zero(h + cursor, begin - cursor))
            return make_error(LSNIF_ERR_RESERVED, cursor,
                              "padding bytes %" PRIu64 "..%" PRIu64 " are not zero", cursor, begin - 1);
        cursor = end;
    }
    if (!all_zero(h + cursor, file_size - cursor))
        return make_error(LSNIF_ERR_RESERVED, cursor, "padding after the last region is not zero");
    return {};
}

Result<Structure> parse_structure(std::span<const std::uint8_t> b) {
    if (Error e = check_magic(b)) return e;
    if (b.size() < 12)
        return make_error(LSNIF_ERR_TRUNCATED, b.size(), "file is %zu bytes, shorter than the 64-byte header",
                          b.size());
    if (Error e = check_version(b)) return e;
    Structure s;
    std::uint32_t table_crc = 0;
    if (Error e = parse_header(b, s, table_crc)) return e;
    if (Error e = check_section_table(b, s, table_crc)) return e;
    const std::uint64_t table_offset = s.header.table_offset;
    const std::uint64_t table_bytes = std::uint64_t(s.header.section_count) * kEntrySize;
    std::vector<std::pair<std::uint64_t, std::uint64_t>> regions{{0, kHeaderSize},
                                                                 {table_offset, table_offset + table_bytes}};
    for (std::uint32_t i = 0; i < s.header.section_count; ++i) {
        Entry en{};
        if (Error e = parse_entry(b, i, table_offset + std::uint64_t(i) * kEntrySize, s, en)) return e;
        if (en.stored_size) regions.push_back({en.offset, en.offset + en.stored_size});
        s.entries.push_back(en);
    }
    if (Error e = check_regions(b, std::move(regions), s.header.file_size)) return e;
    return s;
}

// Decodes one payload, checking both checksums. When `out` is null the bytes are
// streamed through a fixed scratch buffer (scan never allocates per declared size).
// `decoded` (optional) is set when decompression ran to exactly raw_size bytes.
Error decode_payload(std::span<const std::uint8_t> b, const Entry& en, std::uint8_t* out,
                     bool* decoded = nullptr) {
    if (decoded) *decoded = false;
    const std::string tag = tag_string(en.tag);
    const std::uint8_t* src = b.data() + en.offset;
    const std::uint32_t stored_crc = crc32c(src, en.stored_size);
    if (stored_crc != en.stored_crc)
        return make_error(LSNIF_ERR_CHECKSUM, en.offset,
                          "section '%s': stored-bytes checksum mismatch (stored %08" PRIx32
                          ", computed %08" PRIx32 ")",
                          tag.c_str(), en.stored_crc, stored_crc);
    std::uint32_t raw_crc = 0;
    if (en.compression == LSNIF_COMPRESSION_NONE) {
        raw_crc = stored_crc;
        if (out && en.raw_size) std::memcpy(out, src, en.raw_size);
    } else {
        // One Zstandard frame (FORMAT.md §4.4): a skippable frame, which the streaming
        // decoder would take as zero bytes of content, is not one.
        const std::uint32_t magic = en.stored_size >= 4 ? load_u32(src) : 0;
        if (magic != kZstdFrameMagic)
            return make_error(LSNIF_ERR_DECOMPRESS, en.offset,
                              "section '%s': the stored bytes are not a Zstandard frame (magic %08" PRIx32
                              ")",
                              tag.c_str(), magic);
        std::unique_ptr<ZSTD_DCtx, decltype(&ZSTD_freeDCtx)> dctx(ZSTD_createDCtx(), ZSTD_freeDCtx);
        if (!dctx) return make_error(LSNIF_ERR_OUT_OF_MEMORY, en.offset, "zstd context allocation failed");
        // Bound decoder memory regardless of what the frame header asks for.
        ZSTD_DCtx_setParameter(dctx.get(), ZSTD_d_windowLogMax, 27);
        std::vector<std::uint8_t> scratch;
        if (!out) scratch.resize(std::size_t{1} << 17);
        ZSTD_inBuffer in{src, en.stored_size, 0};
        std::uint64_t produced = 0;
        std::size_t ret = 1;
        while (true) {
            std::uint8_t* dst = out ? out + produced : scratch.data();
            // One extra byte of room beyond raw_size detects frames that decode longer.
            std::uint64_t room = out ? en.raw_size - produced : scratch.size();
            std::uint8_t overflow_probe;
            if (out && room == 0) dst = &overflow_probe, room = 1;
            ZSTD_outBuffer ob{dst, std::size_t(room), 0};
            ret = ZSTD_decompressStream(dctx.get(), &ob, &in);
            if (ZSTD_isError(ret))
                return make_error(LSNIF_ERR_DECOMPRESS, en.offset, "section '%s': zstd error: %s",
                                  tag.c_str(), ZSTD_getErrorName(ret));
            if (ob.pos) raw_crc = crc32c(dst, ob.pos, raw_crc);
            produced += ob.pos;
            if (produced > en.raw_size)
                return make_error(LSNIF_ERR_DECOMPRESS, en.offset,
                                  "section '%s': decompresses to more than the declared %" PRIu64 " bytes",
                                  tag.c_str(), en.raw_size);
            if (ret == 0) break;  // frame complete
            if (in.pos == in.size && ob.pos < ob.size)
                return make_error(LSNIF_ERR_DECOMPRESS, en.offset, "section '%s': zstd frame is incomplete",
                                  tag.c_str());
        }
        if (in.pos != in.size)
            return make_error(LSNIF_ERR_DECOMPRESS, en.offset,
                              "section '%s': %zu trailing bytes after the zstd frame", tag.c_str(),
                              in.size - in.pos);
        if (produced != en.raw_size)
            return make_error(LSNIF_ERR_DECOMPRESS, en.offset,
                              "section '%s': decompressed to %" PRIu64 " bytes, declared %" PRIu64,
                              tag.c_str(), produced, en.raw_size);
    }
    if (decoded) *decoded = true;
    if (raw_crc != en.raw_crc)
        return make_error(LSNIF_ERR_CHECKSUM, en.offset,
                          "section '%s': uncompressed checksum mismatch (stored %08" PRIx32
                          ", computed %08" PRIx32 ")",
                          tag.c_str(), en.raw_crc, raw_crc);
    return {};
}

const Entry* find_entry(const Structure& s, std::uint32_t tag) {
    for (const Entry& e : s.entries)
        if (e.tag == tag) return &e;
    return nullptr;
}

template <class F>
auto guard(F&& f) -> decltype(f()) {
    try {
        return f();
    } catch (const std::bad_alloc&) {
        return Error{LSNIF_ERR_OUT_OF_MEMORY, UINT64_MAX, "out of memory"};
    } catch (const std::exception& e) {
        return Error{LSNIF_ERR_INTERNAL, UINT64_MAX, std::string("internal error: ") + e.what()};
    }
}

std::uint64_t grid_bytes(const ModelDesc& d) {
    return d.grid_raw_size();
}

std::uint64_t mlp_bytes(const ModelDesc& d) {
    std::uint64_t n = 0;
    for (std::uint32_t k = 0; k < d.layer_count(); ++k) {
        const auto [o, i] = d.layer_shape(k);
        n += std::uint64_t(o) * i + o;
    }
    return n * 2;
}

std::uint64_t occupancy_bytes(const ModelDesc& d) {
    return (d.voxel_count() + 7) / 8;
}

}  // namespace

// ---- public helpers -------------------------------------------------------------------

std::uint32_t crc32c(const void* data, std::size_t size, std::uint32_t crc) {
    const auto& t = crc_table().t;
    const auto* p = static_cast<const std::uint8_t*>(data);
    crc = ~crc;
    while (size >= 8) {  // slicing-by-8
        const std::uint32_t lo = load_u32(p) ^ crc, hi = load_u32(p + 4);
        crc = t[7][lo & 0xFF] ^ t[6][(lo >> 8) & 0xFF] ^ t[5][(lo >> 16) & 0xFF] ^ t[4][lo >> 24] ^
              t[3][hi & 0xFF] ^ t[2][(hi >> 8) & 0xFF] ^ t[1][(hi >> 16) & 0xFF] ^ t[0][hi >> 24];
        p += 8;
        size -= 8;
    }
    while (size--) crc = (crc >> 8) ^ t[0][(crc ^ *p++) & 0xFF];
    return ~crc;
}

std::string tag_string(std::uint32_t tag) {
    std::string s;
    for (int i = 0; i < 4; ++i) {
        const unsigned c = (tag >> (8 * i)) & 0xFFu;
        if (c >= 0x20 && c <= 0x7E && c != '\\')
            s += char(c);
        else {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\x%02X", c);
            s += buf;
        }
    }
    return s;
}

bool ModelDesc::level_dense(std::uint32_t level) const {
    const std::uint64_t v = std::uint64_t(level_resolution[level]) + 1;
    return v * v * v <= table_size();
}

std::uint64_t ModelDesc::level_entries(std::uint32_t level) const {
    const std::uint64_t v = std::uint64_t(level_resolution[level]) + 1;
    return level_dense(level) ? v * v * v : table_size();
}

std::pair<std::uint32_t, std::uint32_t> ModelDesc::layer_shape(std::uint32_t layer) const {
    const std::uint32_t in = layer == 0 ? input_width() : hidden_width[layer - 1];
    const std::uint32_t out = layer < hidden_width.size() ? hidden_width[layer] : output_count();
    return {out, in};
}

std::uint64_t ModelDesc::grid_value_count() const {
    std::uint64_t n = 0;
    for (std::uint32_t l = 0; l < level_count(); ++l) n += level_entries(l) * features_per_level;
    return n;
}

std::uint64_t ModelDesc::grid_raw_size() const {
    // FORMAT.md §6.4 / §6.4.1. Both terms are bounded (<= 2^24 entries x 8 features x 8
    // levels), so nothing wraps even before validate_desc has checked the result.
    if (grid_encoding == GridEncoding::u8_affine)
        return 8 * std::uint64_t(level_count()) + grid_value_count();
    return 2 * grid_value_count();
}

std::uint64_t ModelDesc::parameter_count() const {
    return grid_value_count() + mlp_bytes(*this) / 2;
}

Error validate_desc(const ModelDesc& d) {
    auto bad = [](const char* fmt, auto... args) {
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX, fmt, args...);
    };
    if (d.grid_resolution < 1 || d.grid_resolution > kMaxGridResolution)
        return bad("grid_resolution %u outside 1..%u", d.grid_resolution, kMaxGridResolution);
    if (d.max_points < 1 || d.max_points > kMaxPoints)
        return bad("max_points %u outside 1..%u", d.max_points, kMaxPoints);
    if (d.level_count() < 1 || d.level_count() > LSNIF_MAX_LEVELS)
        return bad("level_count %u outside 1..%u", d.level_count(), LSNIF_MAX_LEVELS);
    if (d.features_per_level < 1 || d.features_per_level > kMaxFeatures)
        return bad("features_per_level %u outside 1..%u", d.features_per_level, kMaxFeatures);
    if (d.log2_table_size < kMinLog2TableSize || d.log2_table_size > kMaxLog2TableSize)
        return bad("log2_table_size %u outside %u..%u", d.log2_table_size, kMinLog2TableSize,
                   kMaxLog2TableSize);
    for (std::uint32_t l = 0; l < d.level_count(); ++l)
        if (d.level_resolution[l] < 1 || d.level_resolution[l] > kMaxLevelResolution)
            return bad("level_resolution[%u] = %u outside 1..%u", l, d.level_resolution[l],
                       kMaxLevelResolution);
    if (d.hidden_width.empty() || d.hidden_width.size() > LSNIF_MAX_HIDDEN_LAYERS)
        return bad("hidden_layer_count %zu outside 1..%u", d.hidden_width.size(), LSNIF_MAX_HIDDEN_LAYERS);
    for (std::size_t k = 0; k < d.hidden_width.size(); ++k)
        if (d.hidden_width[k] < 1 || d.hidden_width[k] > kMaxHiddenWidth)
            return bad("hidden_width[%zu] = %u outside 1..%u", k, d.hidden_width[k], kMaxHiddenWidth);
    if (d.material_count > kMaxMaterials)
        return bad("material_count %u exceeds %u", d.material_count, kMaxMaterials);
    if (d.activation != 0) return bad("activation %u unknown (0 = ReLU)", d.activation);
    if (d.distance_encoding > LSNIF_DISTANCE_FIRST_ENTRY_DIAGONAL)
        return bad("distance_encoding %u unknown", d.distance_encoding);
    if (std::uint32_t(d.grid_encoding) > LSNIF_GRID_U8_AFFINE)
        return bad("grid_encoding %u unknown", std::uint32_t(d.grid_encoding));
    if (d.ray_inputs & ~kRayInputsKnown) return bad("ray_inputs 0x%x has unknown bits", d.ray_inputs);
    for (int i = 0; i < 3; ++i) {
        if (!std::isfinite(d.box_min[i]) || !std::isfinite(d.box_max[i]))
            return Error{LSNIF_ERR_NONFINITE, UINT64_MAX, "box has a NaN or infinite coordinate"};
        if (!(d.box_max[i] > d.box_min[i]))
            return bad("box axis %d is empty or inverted (min %g, max %g)", i, double(d.box_min[i]),
                       double(d.box_max[i]));
    }
    if (grid_bytes(d) > kMaxSectionRawSize)
        return bad("hash-grid tables need %llu bytes, above the %llu-byte section limit",
                   (unsigned long long)grid_bytes(d), (unsigned long long)kMaxSectionRawSize);
    return {};
}

Result<ModelData> make_empty_model(const ModelDesc& desc) {
    if (Error e = validate_desc(desc)) return e;
    return guard([&]() -> Result<ModelData> {
        ModelData m;
        m.desc = desc;
        m.occupancy.assign(occupancy_bytes(desc), 0);
        const bool quantized = desc.grid_encoding == GridEncoding::u8_affine;
        for (std::uint32_t l = 0; l < desc.level_count(); ++l) {
            const std::uint64_t values = desc.level_entries(l) * desc.features_per_level;
            if (quantized)
                m.grid_u8.emplace_back(values, 0), m.grid_affine.push_back({});
            else
                m.grid.emplace_back(values, 0);
        }
        m.version_minor = desc.minor_version();
        for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
            const auto [o, i] = desc.layer_shape(k);
            m.weights.emplace_back(std::size_t(o) * i, 0);
            m.biases.emplace_back(o, 0);
        }
        m.metadata_json = "{}";
        return m;
    });
}

namespace {

// The grid arrays against the descriptor, then their content (FORMAT.md §7.2 E10), level
// 0 first. Exactly the representation desc.grid_encoding names may be filled.
Error validate_grid(const ModelData& m) {
    const ModelDesc& d = m.desc;
    const bool quantized = d.grid_encoding == GridEncoding::u8_affine;
    const std::size_t levels = quantized ? m.grid_u8.size() : m.grid.size();
    if (levels != d.level_count() || (quantized && m.grid_affine.size() != d.level_count()))
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "%zu grid levels, expected %u", levels,
                          d.level_count());
    if (quantized ? !m.grid.empty() : (!m.grid_u8.empty() || !m.grid_affine.empty()))
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX,
                          "grid arrays of another encoding than grid_encoding %u",
                          std::uint32_t(d.grid_encoding));
    for (std::uint32_t l = 0; l < d.level_count(); ++l) {
        const std::uint64_t want = d.level_entries(l) * d.features_per_level;
        const std::size_t have = quantized ? m.grid_u8[l].size() : m.grid[l].size();
        if (have != want)
            return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "grid level %u has %zu values, expected %llu", l,
                              have, (unsigned long long)want);
        if (quantized) {
            // FORMAT.md §6.4.1: with finite scale >= 0 the dequantization is monotone in q,
            // so finite results at q = 0 and q = 255 make every byte's value finite.
            const LevelAffine a = m.grid_affine[l];
            if (!std::isfinite(a.scale) || !std::isfinite(a.offset))
                return make_error(LSNIF_ERR_NONFINITE, UINT64_MAX,
                                  "grid level %u: scale %g or offset %g is not finite", l, double(a.scale),
                                  double(a.offset));
            if (!(a.scale >= 0.0f))
                return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "grid level %u: scale %g is negative", l,
                                  double(a.scale));
            if (!std::isfinite(dequantize_u8(0, a.scale, a.offset)) ||
                !std::isfinite(dequantize_u8(255, a.scale, a.offset)))
                return make_error(
                    LSNIF_ERR_NONFINITE, UINT64_MAX,
                    "grid level %u: dequantized value of byte 255 (scale %g, offset %g) is not finite", l,
                    double(a.scale), double(a.offset));
            continue;
        }
        for (std::size_t i = 0; i < m.grid[l].size(); ++i)
            if (!half_is_finite(m.grid[l][i]))
                return make_error(LSNIF_ERR_NONFINITE, UINT64_MAX,
                                  "grid level %u entry %zu feature %zu is not finite", l,
                                  i / d.features_per_level, i % d.features_per_level);
    }
    return {};
}

}  // namespace

Error validate_model(const ModelData& m) {
    if (Error e = validate_desc(m.desc)) return e;
    const ModelDesc& d = m.desc;
    if (m.occupancy.size() != occupancy_bytes(d))
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "occupancy has %zu bytes, expected %llu",
                          m.occupancy.size(), (unsigned long long)occupancy_bytes(d));
    const std::uint64_t bits = d.voxel_count();
    if (bits % 8 && (m.occupancy.back() >> (bits % 8)))
        return make_error(LSNIF_ERR_RESERVED, UINT64_MAX, "unused trailing occupancy bits are not zero");
    if (Error e = validate_grid(m)) return e;
    if (m.weights.size() != d.layer_count() || m.biases.size() != d.layer_count())
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "MLP has %zu weight / %zu bias arrays, expected %u",
                          m.weights.size(), m.biases.size(), d.layer_count());
    for (std::uint32_t k = 0; k < d.layer_count(); ++k) {
        const auto [o, i] = d.layer_shape(k);
        if (m.weights[k].size() != std::size_t(o) * i || m.biases[k].size() != o)
            return make_error(LSNIF_ERR_MODEL, UINT64_MAX,
                              "MLP layer %u arrays have the wrong size (expected %u x %u)", k, o, i);
        for (std::size_t j = 0; j < m.weights[k].size(); ++j)
            if (!half_is_finite(m.weights[k][j]))
                return make_error(LSNIF_ERR_NONFINITE, UINT64_MAX,
                                  "MLP layer %u weight [%zu][%zu] is not finite", k, j / i, j % i);
        for (std::size_t j = 0; j < o; ++j)
            if (!half_is_finite(m.biases[k][j]))
                return make_error(LSNIF_ERR_NONFINITE, UINT64_MAX, "MLP layer %u bias [%zu] is not finite", k,
                                  j);
    }
    if (m.metadata_json.size() > kMaxMetadataSize)
        return make_error(LSNIF_ERR_LIMIT, UINT64_MAX, "metadata is %zu bytes, limit %llu",
                          m.metadata_json.size(), (unsigned long long)kMaxMetadataSize);
    if (!valid_utf8(reinterpret_cast<const std::uint8_t*>(m.metadata_json.data()), m.metadata_json.size()))
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX, "metadata is not NUL-free UTF-8");
    // The reader has no JSON parser (format/ depends on zstd only); it checks the
    // object's braces so an empty or truncated text never passes as metadata.
    const std::size_t first = m.metadata_json.find_first_not_of(" \t\r\n");
    const std::size_t last = m.metadata_json.find_last_not_of(" \t\r\n");
    if (first == std::string::npos || m.metadata_json[first] != '{' || m.metadata_json[last] != '}')
        return make_error(LSNIF_ERR_MODEL, UINT64_MAX,
                          "metadata is not a JSON object (must start with '{' and end with '}')");
    return {};
}

// ---- writer ---------------------------------------------------------------------------

std::vector<std::uint8_t> encode_descriptor(const ModelDesc& desc) {
    return encode_desc(desc);
}

std::vector<RawSection> model_sections(const ModelData& m) {
    std::vector<RawSection> secs;
    secs.push_back({kTagMeta, LSNIF_SECTION_REQUIRED, {m.metadata_json.begin(), m.metadata_json.end()}});
    secs.push_back({kTagModel, LSNIF_SECTION_REQUIRED, encode_desc(m.desc)});
    secs.push_back({kTagOccupancy, LSNIF_SECTION_REQUIRED, m.occupancy});
    auto append_halves = [](std::vector<std::uint8_t>& out, const std::vector<std::uint16_t>& v) {
        const std::size_t at = out.size();
        out.resize(at + 2 * v.size());
        for (std::size_t i = 0; i < v.size(); ++i) store_u16(out.data() + at + 2 * i, v[i]);
    };
    RawSection grid{kTagGrid, LSNIF_SECTION_REQUIRED, {}};
    if (m.desc.grid_encoding == GridEncoding::u8_affine) {
        // FORMAT.md §6.4.1: all (scale, offset) pairs first, then the bytes of every level.
        grid.raw.resize(8 * m.grid_affine.size());
        for (std::size_t l = 0; l < m.grid_affine.size(); ++l) {
            store_f32(grid.raw.data() + 8 * l, m.grid_affine[l].scale);
            store_f32(grid.raw.data() + 8 * l + 4, m.grid_affine[l].offset);
        }
        for (const auto& level : m.grid_u8) grid.raw.insert(grid.raw.end(), level.begin(), level.end());
    } else {
        for (const auto& level : m.grid) append_halves(grid.raw, level);
    }
    secs.push_back(std::move(grid));
    RawSection mlp{kTagMlp, LSNIF_SECTION_REQUIRED, {}};
    for (std::size_t k = 0; k < m.weights.size() && k < m.biases.size(); ++k) {
        append_halves(mlp.raw, m.weights[k]);
        append_halves(mlp.raw, m.biases[k]);
    }
    secs.push_back(std::move(mlp));
    return secs;
}

Result<std::vector<std::uint8_t>> assemble(const std::vector<RawSection>& secs, int zstd_level,
                                           std::uint16_t major, std::uint16_t minor) {
    return guard([&]() -> Result<std::vector<std::uint8_t>> {
        if (secs.empty() || secs.size() > kMaxSections)
            return make_error(LSNIF_ERR_LIMIT, UINT64_MAX, "section count %zu outside 1..%u", secs.size(),
                              kMaxSections);
        for (std::size_t i = 0; i < secs.size(); ++i) {
            if (secs[i].raw.size() > kMaxSectionRawSize)
                return make_error(LSNIF_ERR_LIMIT, UINT64_MAX,
                                  "section '%s' is %zu bytes, above the %llu-byte limit",
                                  tag_string(secs[i].tag).c_str(), secs[i].raw.size(),
                                  (unsigned long long)kMaxSectionRawSize);
            for (std::size_t j = 0; j < i; ++j)
                if (secs[j].tag == secs[i].tag)
                    return make_error(LSNIF_ERR_INVALID_ARGUMENT, UINT64_MAX, "duplicate section tag '%s'",
                                      tag_string(secs[i].tag).c_str());
        }
        const std::uint64_t table_offset = kHeaderSize;
        std::uint64_t cursor = align_up(table_offset + secs.size() * kEntrySize);
        std::vector<std::uint8_t> table(secs.size() * kEntrySize, 0);
        std::vector<std::vector<std::uint8_t>> stored(secs.size());
        for (std::size_t i = 0; i < secs.size(); ++i) {
            const auto& raw = secs[i].raw;
            std::uint32_t compression = LSNIF_COMPRESSION_NONE;
            if (zstd_level > 0 && !raw.empty()) {
                std::vector<std::uint8_t> z(ZSTD_compressBound(raw.size()));
                const std::size_t n = ZSTD_compress(z.data(), z.size(), raw.data(), raw.size(), zstd_level);
                if (ZSTD_isError(n))
                    return make_error(LSNIF_ERR_INTERNAL, UINT64_MAX, "zstd compression failed: %s",
                                      ZSTD_getErrorName(n));
                if (n < raw.size()) {  // keep incompressible payloads raw: cheaper to read
                    z.resize(n);
                    stored[i] = std::move(z);
                    compression = LSNIF_COMPRESSION_ZSTD;
                }
            }
            if (compression == LSNIF_COMPRESSION_NONE) stored[i] = raw;
            std::uint8_t* e = table.data() + i * kEntrySize;
            store_u32(e, secs[i].tag);
            store_u32(e + 4, secs[i].flags);
            store_u32(e + 8, compression);
            store_u64(e + 16, cursor);
            store_u64(e + 24, stored[i].size());
            store_u64(e + 32, raw.size());
            store_u32(e + 40, crc32c(stored[i].data(), stored[i].size()));
            store_u32(e + 44, crc32c(raw.data(), raw.size()));
            cursor = align_up(cursor + stored[i].size());
        }
        const std::uint64_t file_size = cursor;
        if (file_size > kMaxFileSize)
            return make_error(LSNIF_ERR_LIMIT, UINT64_MAX,
                              "file would be %llu bytes, above the %llu-byte limit",
                              (unsigned long long)file_size, (unsigned long long)kMaxFileSize);
        std::vector<std::uint8_t> out(file_size, 0);
        std::uint8_t* h = out.data();
        std::copy(kMagic.begin(), kMagic.end(), h);
        store_u16(h + 8, major);
        store_u16(h + 10, minor);
        store_u32(h + 12, kHeaderSize);
        store_u64(h + 16, file_size);
        store_u64(h + 24, table_offset);
        store_u32(h + 32, std::uint32_t(secs.size()));
        store_u32(h + 36, kEntrySize);
        store_u32(h + 40, crc32c(table.data(), table.size()));
        store_u32(h + 60, crc32c(h, 60));
        std::copy(table.begin(), table.end(), h + table_offset);
        for (std::size_t i = 0; i < secs.size(); ++i)
            std::copy(stored[i].begin(), stored[i].end(), h + load_u64(table.data() + i * kEntrySize + 16));
        return out;
    });
}

Result<std::vector<std::uint8_t>> serialize(const ModelData& m, const WriteOptions& options) {
    if (Error e = validate_model(m)) return e;
    return guard([&]() -> Result<std::vector<std::uint8_t>> {
        std::vector<RawSection> secs = model_sections(m);
        for (const ExtraSection& x : options.extra_sections) {
            if (!tag_printable(x.tag) || is_known_tag(x.tag))
                return make_error(LSNIF_ERR_INVALID_ARGUMENT, UINT64_MAX,
                                  "extra section tag '%s' is not printable or collides with a v1 tag",
                                  tag_string(x.tag).c_str());
            secs.push_back({x.tag, x.required ? LSNIF_SECTION_REQUIRED : 0u, x.payload});
        }
        // FORMAT.md §2.4: the lowest version that can express the model, whatever version
        // m was read from, so fp16 models stay 1.0 files (byte-identical to a 1.0 writer's).
        return assemble(secs, options.zstd_level, LSNIF_VERSION_MAJOR, m.desc.minor_version());
    });
}

Error write_bytes_atomically(const std::string& path, std::span<const std::uint8_t> bytes) {
    // The temporary lives next to the target so rename() stays within one filesystem.
    std::string tmp = path + ".tmp-XXXXXX";
    const int fd = ::mkstemp(tmp.data());
    if (fd < 0)
        return make_error(LSNIF_ERR_IO, UINT64_MAX, "cannot create a temporary file next to '%s': %s",
                          path.c_str(), std::strerror(errno));
    std::size_t done = 0;
    int err = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
        if (n < 0) {
            if (errno == EINTR) continue;
            err = errno;
            break;
        }
        done += std::size_t(n);
    }
    if (!err && ::fsync(fd) != 0) err = errno;
    if (::close(fd) != 0 && !err) err = errno;
    if (!err && ::chmod(tmp.c_str(), 0644) != 0) err = errno;
    if (!err && std::rename(tmp.c_str(), path.c_str()) != 0) err = errno;
    if (err) {
        ::unlink(tmp.c_str());
        return make_error(LSNIF_ERR_IO, UINT64_MAX, "cannot write '%s': %s", path.c_str(),
                          std::strerror(err));
    }
    return {};
}

Error write_text_atomically(const std::string& path, std::string_view text) {
    return write_bytes_atomically(path, {reinterpret_cast<const std::uint8_t*>(text.data()), text.size()});
}

Error write_file(const std::string& path, const ModelData& model, const WriteOptions& options) {
    auto bytes = serialize(model, options);
    if (!bytes) return bytes.error();
    return write_bytes_atomically(path, bytes.value());
}

// ---- reader ---------------------------------------------------------------------------

Result<std::vector<std::uint8_t>> read_file_bytes(const std::string& path) {
    return guard([&]() -> Result<std::vector<std::uint8_t>> {
        std::error_code ec;
        if (std::filesystem::is_directory(path, ec))
            return make_error(LSNIF_ERR_IO, UINT64_MAX, "'%s' is a directory", path.c_str());
        std::FILE* f = std::fopen(path.c_str(), "rb");
        if (!f)
            return make_error(LSNIF_ERR_IO, UINT64_MAX, "cannot open '%s': %s", path.c_str(),
                              std::strerror(errno));
        std::vector<std::uint8_t> data;
        std::uint8_t buf[1 << 16];
        std::size_t n;
        while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) {
            // A foreign file is rejected by its signature; no need to read all of it.
            if (data.empty() && (n < 4 || buf[1] != 'L' || buf[2] != 'S' || buf[3] != 'N')) {
                data.assign(buf, buf + n);
                break;
            }
            if (data.size() + n > kMaxFileSize) {
                std::fclose(f);
                return make_error(LSNIF_ERR_LIMIT, UINT64_MAX, "'%s' is larger than %llu bytes", path.c_str(),
                                  (unsigned long long)kMaxFileSize);
            }
            data.insert(data.end(), buf, buf + n);
        }
        const bool failed = std::ferror(f);
        std::fclose(f);
        if (failed) return make_error(LSNIF_ERR_IO, UINT64_MAX, "error reading '%s'", path.c_str());
        return data;
    });
}

Result<ScanResult> scan(std::span<const std::uint8_t> bytes) {
    return guard([&]() -> Result<ScanResult> {
        auto s = parse_structure(bytes);
        if (!s) return s.error();
        ScanResult r;
        r.header = s->header;
        for (const Entry& en : s->entries) {
            lsnif_section_info info{};
            const std::string t = tag_string(en.tag);
            std::memcpy(info.tag, t.c_str(), std::min<std::size_t>(4, t.size()));
            info.known = is_known_tag(en.tag);
            info.flags = en.flags;
            info.compression = en.compression;
            info.offset = en.offset;
            info.stored_size = en.stored_size;
            info.raw_size = en.raw_size;
            info.stored_crc32c = en.stored_crc;
            info.raw_crc32c = en.raw_crc;
            bool decoded = false;
            Error e = decode_payload(bytes, en, nullptr, &decoded);
            info.checksum_ok = !e;
            info.decoded = decoded;
            info.payload_status = e.status;
            if (e && !r.first_payload_error) r.first_payload_error = e;
            r.sections.push_back(info);
        }
        return r;
    });
}

namespace {

// FORMAT.md §7.2 E1: the five version 1 sections are present, checked in that order.
Error check_required_sections(const Structure& s) {
    const std::uint32_t required[] = {kTagMeta, kTagModel, kTagOccupancy, kTagGrid, kTagMlp};
    for (std::uint32_t tag : required)
        if (!find_entry(s, tag))
            return make_error(LSNIF_ERR_MISSING_SECTION, s.header.table_offset,
                              "required section '%s' is missing", tag_string(tag).c_str());
    return {};
}

// FORMAT.md §7.2 E2-E4: the MODL section, decoded and checked. Requires the section to be
// present (check_required_sections).
Result<ModelDesc> read_descriptor(std::span<const std::uint8_t> bytes, const Structure& s) {
    const Entry& me = *find_entry(s, kTagModel);
    if (me.raw_size != kDescriptorSize)
        return make_error(LSNIF_ERR_MODEL, me.entry_offset + 32,
                          "MODL section: raw size %" PRIu64 ", expected exactly %u", me.raw_size,
                          kDescriptorSize);
    std::vector<std::uint8_t> desc_bytes(kDescriptorSize);
    if (Error e = decode_payload(bytes, me, desc_bytes.data())) return e;
    return decode_desc(desc_bytes, me.offset, s.header.version_minor);
}

// FORMAT.md §7.2 E5-E6: the OCCU, GRID and MLPW raw sizes are exactly what `d` implies and
// META is within its limit, so buffers sized from these entries are bounded.
Error check_section_sizes(const Structure& s, const ModelDesc& d) {
    auto expect_size = [&](std::uint32_t tag, std::uint64_t want) -> Error {
        const Entry& e = *find_entry(s, tag);
        if (e.raw_size != want)
            return make_error(LSNIF_ERR_MODEL, e.entry_offset + 32,
                              "section '%s': raw size %" PRIu64 " does not match the %" PRIu64
                              " bytes the model descriptor implies",
                              tag_string(tag).c_str(), e.raw_size, want);
        return {};
    };
    if (Error e = expect_size(kTagOccupancy, occupancy_bytes(d))) return e;
    if (Error e = expect_size(kTagGrid, grid_bytes(d))) return e;
    if (Error e = expect_size(kTagMlp, mlp_bytes(d))) return e;
    const Entry& meta = *find_entry(s, kTagMeta);
    if (meta.raw_size > kMaxMetadataSize)
        return make_error(LSNIF_ERR_LIMIT, meta.entry_offset + 32,
                          "META section: %" PRIu64 " bytes exceeds the %" PRIu64 "-byte limit", meta.raw_size,
                          kMaxMetadataSize);
    return {};
}

// The payload of `e`, decoded into `raw`, which is resized to e.raw_size first.
Error read_section(std::span<const std::uint8_t> bytes, const Entry& e, std::vector<std::uint8_t>& raw) {
    raw.resize(e.raw_size);
    return decode_payload(bytes, e, raw.data());
}

// FORMAT.md §7.2 E7: the META section into m.metadata_json, NUL-free well-formed UTF-8.
Error read_metadata(std::span<const std::uint8_t> bytes, const Structure& s, ModelData& m) {
    const Entry& meta = *find_entry(s, kTagMeta);
    std::vector<std::uint8_t> buf;
    if (Error e = read_section(bytes, meta, buf)) return e;
    if (!valid_utf8(buf.data(), buf.size()))
        return make_error(LSNIF_ERR_MODEL, meta.offset, "META section: not NUL-free UTF-8 text");
    m.metadata_json.assign(buf.begin(), buf.end());
    return {};
}

// `n` little-endian 16-bit values from `raw` at byte `at`, which moves past them. The caller
// has checked that they are inside `raw`.
std::vector<std::uint16_t> take_halves(const std::vector<std::uint8_t>& raw, std::size_t& at, std::size_t n) {
    std::vector<std::uint16_t> v(n);
    for (std::size_t i = 0; i < n; ++i) v[i] = load_u16(raw.data() + at + 2 * i);
    at += 2 * n;
    return v;
}

// The GRID section into m.grid (fp16) or into m.grid_affine and m.grid_u8 (FORMAT.md
// §6.4.1), as m.desc.grid_encoding says. Its size was checked against the descriptor (E5).
Error read_grid(std::span<const std::uint8_t> bytes, const Structure& s, ModelData& m) {
    const ModelDesc& d = m.desc;
    std::vector<std::uint8_t> buf;
    if (Error e = read_section(bytes, *find_entry(s, kTagGrid), buf)) return e;
    std::size_t at = 0;
    // Exact capacities: what a handle holds is counted at the size allocated (lsnif_info).
    if (d.grid_encoding == GridEncoding::u8_affine) {
        m.grid_affine.reserve(d.level_count());
        m.grid_u8.reserve(d.level_count());
        for (std::uint32_t l = 0; l < d.level_count(); ++l)
            m.grid_affine.push_back({load_f32(buf.data() + 8 * l), load_f32(buf.data() + 8 * l + 4)});
        at = 8 * std::size_t(d.level_count());
        for (std::uint32_t l = 0; l < d.level_count(); ++l) {
            const std::size_t n = d.level_entries(l) * d.features_per_level;
            m.grid_u8.emplace_back(buf.begin() + at, buf.begin() + at + n);
            at += n;
        }
    } else {
        m.grid.reserve(d.level_count());
        for (std::uint32_t l = 0; l < d.level_count(); ++l)
            m.grid.push_back(take_halves(buf, at, d.level_entries(l) * d.features_per_level));
    }
    return {};
}

// The MLPW section into m.weights and m.biases, layer by layer, each layer's weights then
// its biases (FORMAT.md §6.5). Its size was checked against the descriptor (E5).
Error read_mlp(std::span<const std::uint8_t> bytes, const Structure& s, ModelData& m) {
    std::vector<std::uint8_t> buf;
    if (Error e = read_section(bytes, *find_entry(s, kTagMlp), buf)) return e;
    std::size_t at = 0;
    m.weights.reserve(m.desc.layer_count());
    m.biases.reserve(m.desc.layer_count());
    for (std::uint32_t k = 0; k < m.desc.layer_count(); ++k) {
        const auto [o, i] = m.desc.layer_shape(k);
        m.weights.push_back(take_halves(buf, at, std::size_t(o) * i));
        m.biases.push_back(take_halves(buf, at, o));
    }
    return {};
}

}  // namespace

Result<ModelData> read_model(std::span<const std::uint8_t> bytes) {
    return guard([&]() -> Result<ModelData> {
        auto st = parse_structure(bytes);
        if (!st) return st.error();
        const Structure& s = st.value();
        if (Error e = check_required_sections(s)) return e;
        // Decode the descriptor first: it fixes every other section's exact size, so
        // nothing is allocated from an unchecked declaration.
        auto desc = read_descriptor(bytes, s);
        if (!desc) return desc.error();
        if (Error e = check_section_sizes(s, desc.value())) return e;

        ModelData m;
        m.desc = desc.value();
        m.version_major = s.header.version_major;
        m.version_minor = s.header.version_minor;
        if (Error e = read_metadata(bytes, s, m)) return e;
        m.occupancy.resize(occupancy_bytes(m.desc));
        if (Error e = decode_payload(bytes, *find_entry(s, kTagOccupancy), m.occupancy.data())) return e;
        if (Error e = read_grid(bytes, s, m)) return e;
        if (Error e = read_mlp(bytes, s, m)) return e;
        // Skipped: unknown optional sections (FORMAT.md §2), but their checksums still count.
        for (const Entry& e : s.entries)
            if (!is_known_tag(e.tag))
                if (Error err = decode_payload(bytes, e, nullptr)) return err;
        if (Error e = validate_model(m)) {
            e.message = "model content: " + e.message;
            return e;
        }
        return m;
    });
}

}  // namespace lsnif::format
