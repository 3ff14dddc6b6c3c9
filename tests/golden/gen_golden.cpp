// Generates the golden files of tests/data deterministically:
//   gen_golden OUTDIR      writes OUTDIR/valid/*.lsnif and OUTDIR/invalid/*.lsnif
// The committed copies are checked byte for byte against a fresh run (test
// golden_files_are_reproducible), so the writer can never drift silently. Each invalid
// file breaks exactly one rule of FORMAT.md; its expected error is committed next to it
// as NAME.expected and checked by the converter tests.
#include <lsnif/format/container.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

using namespace lsnif::format;
namespace fs = std::filesystem;

namespace {

// splitmix64: tiny, portable and stable across platforms (std:: distributions are not).
struct Rng {
    std::uint64_t s;
    std::uint64_t next() {
        std::uint64_t z = (s += 0x9E3779B97F4A7C15ull);
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
        return z ^ (z >> 31);
    }
    float uniform(float lo, float hi) { return lo + (hi - lo) * float(next() >> 40) / float(1 << 24); }
};

std::string metadata_for(const ModelDesc& d, const char* name) {
    std::string levels, hidden;
    for (auto r : d.level_resolution) levels += (levels.empty() ? "" : ", ") + std::to_string(r);
    for (auto w : d.hidden_width) hidden += (hidden.empty() ? "" : ", ") + std::to_string(w);
    char buf[2048];
    std::snprintf(
        buf, sizeof buf,
        "{\n"
        "  \"format\": \"lsnif-metadata/1\",\n"
        "  \"tool\": {\"name\": \"lsnif-gen-golden\", \"version\": \"0.1.0\"},\n"
        "  \"object\": {\"name\": \"%s\", \"source_hash\": \"fnv1a64:%016llx\",\n"
        "             \"box_min\": [%.9g, %.9g, %.9g], \"box_max\": [%.9g, %.9g, %.9g]},\n"
        "  \"model\": {\"grid_resolution\": %u, \"max_points\": %u, \"level_resolutions\": [%s],\n"
        "            \"features_per_level\": %u, \"log2_table_size\": %u, \"hidden_widths\": [%s],\n"
        "            \"output_count\": %u, \"material_count\": %u, \"activation\": \"relu\",\n"
        "            \"distance_encoding\": \"%s\"%s}\n"
        "}\n",
        name, 0x1234abcdULL * d.grid_resolution, double(d.box_min[0]), double(d.box_min[1]),
        double(d.box_min[2]), double(d.box_max[0]), double(d.box_max[1]), double(d.box_max[2]),
        d.grid_resolution, d.max_points, levels.c_str(), d.features_per_level, d.log2_table_size,
        hidden.c_str(), d.output_count(), d.material_count,
        d.distance_encoding == LSNIF_DISTANCE_SEGMENT ? "segment" : "first_entry_diagonal",
        d.ray_inputs == (kRayInputDirection | kRayInputEntryOffsets)
            ? ", \"ray_inputs\": \"direction+entry_offsets\""
            : "");
    return buf;
}

// A model with a sphere-shell occupancy and pseudo-random weights.
ModelData make_model(const ModelDesc& desc, const char* name, std::uint64_t seed, bool zero_grid = false) {
    auto r = make_empty_model(desc);
    if (!r) {
        std::fprintf(stderr, "gen_golden: %s\n", r.error().message.c_str());
        std::exit(1);
    }
    ModelData m = std::move(r.value());
    m.metadata_json = metadata_for(desc, name);
    const std::uint32_t v = desc.grid_resolution;
    const float c = (v - 1) * 0.5f;
    for (std::uint32_t z = 0; z < v; ++z)
        for (std::uint32_t y = 0; y < v; ++y)
            for (std::uint32_t x = 0; x < v; ++x) {
                const float d2 = (x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c);
                const float rad = 0.4f * v;
                if (d2 <= rad * rad && d2 >= (rad - 1.5f) * (rad - 1.5f)) {
                    const std::uint64_t i = x + std::uint64_t(v) * (y + std::uint64_t(v) * z);
                    m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
                }
            }
    Rng rng{seed};
    if (!zero_grid)
        for (auto& level : m.grid)
            for (auto& h : level) h = float_to_half(rng.uniform(-1e-4f, 1e-4f));
    for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
        const float scale = 1.0f / std::sqrt(float(desc.layer_shape(k).second));
        for (auto& h : m.weights[k]) h = float_to_half(rng.uniform(-scale, scale));
        for (auto& h : m.biases[k]) h = float_to_half(rng.uniform(-0.01f, 0.01f));
    }
    return m;
}

ModelDesc tiny_desc() {
    ModelDesc d;
    d.grid_resolution = 4;
    d.max_points = 2;
    d.level_resolution = {8};
    d.features_per_level = 2;
    d.log2_table_size = 8;
    d.hidden_width = {8};
    d.box_min = {-1.f, -0.5f, -0.25f};
    d.box_max = {1.f, 0.5f, 0.25f};
    return d;
}

void put_u32(std::vector<std::uint8_t>& b, std::size_t at, std::uint32_t v) {
    for (int i = 0; i < 4; ++i) b[at + i] = std::uint8_t(v >> (8 * i));
}
void put_u64(std::vector<std::uint8_t>& b, std::size_t at, std::uint64_t v) {
    for (int i = 0; i < 8; ++i) b[at + i] = std::uint8_t(v >> (8 * i));
}
std::uint32_t get_u32(const std::vector<std::uint8_t>& b, std::size_t at) {
    std::uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v |= std::uint32_t(b[at + i]) << (8 * i);
    return v;
}
std::uint64_t get_u64(const std::vector<std::uint8_t>& b, std::size_t at) {
    return get_u32(b, at) | std::uint64_t(get_u32(b, at + 4)) << 32;
}

// Recomputes the table and header checksums after a deliberate edit, so the file fails
// for the intended reason and not for a checksum.
void reseal(std::vector<std::uint8_t>& b) {
    const std::uint64_t table = get_u64(b, 24);
    const std::uint32_t count = get_u32(b, 32);
    if (table + std::uint64_t(count) * kEntrySize <= b.size())
        put_u32(b, 40, crc32c(b.data() + table, std::size_t(count) * kEntrySize));
    put_u32(b, 60, crc32c(b.data(), 60));
}

std::size_t entry_of(const std::vector<std::uint8_t>& b, std::uint32_t tag) {
    const std::uint64_t table = get_u64(b, 24);
    for (std::uint32_t i = 0; i < get_u32(b, 32); ++i)
        if (get_u32(b, table + i * kEntrySize) == tag) return table + i * kEntrySize;
    std::fprintf(stderr, "gen_golden: tag not found\n");
    std::exit(1);
}

std::vector<std::uint8_t> bytes_of(const Result<std::vector<std::uint8_t>>& r) {
    if (!r) {
        std::fprintf(stderr, "gen_golden: %s\n", r.error().message.c_str());
        std::exit(1);
    }
    return r.value();
}

void write(const fs::path& p, const std::vector<std::uint8_t>& b) {
    std::FILE* f = std::fopen(p.c_str(), "wb");
    if (!f || std::fwrite(b.data(), 1, b.size(), f) != b.size() || std::fclose(f) != 0) {
        std::fprintf(stderr, "gen_golden: cannot write %s\n", p.c_str());
        std::exit(1);
    }
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: gen_golden OUTDIR\n");
        return 2;
    }
    const fs::path out = argv[1];
    fs::create_directories(out / "valid");
    fs::create_directories(out / "invalid");

    // ---- valid -------------------------------------------------------------------------
    const ModelData tiny = make_model(tiny_desc(), "tiny", 1);
    const auto tiny_bytes = bytes_of(serialize(tiny));
    write(out / "valid" / "tiny.lsnif", tiny_bytes);

    ModelDesc dense = tiny_desc();
    dense.max_points = 3;
    dense.level_resolution = {3, 6};  // (3+1)^3 = 64 and (6+1)^3 = 343 <= 2^10: both dense
    dense.log2_table_size = 10;
    dense.hidden_width = {16, 8};
    dense.material_count = 2;
    dense.distance_encoding = LSNIF_DISTANCE_SEGMENT;
    WriteOptions stored;
    stored.zstd_level = 0;
    write(out / "valid" / "dense_uncompressed.lsnif",
          bytes_of(serialize(make_model(dense, "dense", 2), stored)));

    WriteOptions extra;
    extra.extra_sections.push_back({make_tag("XTRA"), false, {'o', 'p', 't', 'i', 'o', 'n', 'a', 'l'}});
    write(out / "valid" / "unknown_optional_section.lsnif", bytes_of(serialize(tiny, extra)));

    ModelDesc v1;  // the v1 dimensions (ModelDesc defaults; grid zero: keeps the file small)
    v1.box_min = {-0.5f, 0.0f, -0.25f};
    v1.box_max = {0.5f, 1.25f, 0.25f};
    write(out / "valid" / "v1_default.lsnif", bytes_of(serialize(make_model(v1, "v1-default", 3, true))));

    // Version 1.1 (FORMAT.md §2.4): a quantized grid, which the writer marks 1.1 ...
    auto quantized = quantize_model(make_model(tiny_desc(), "tiny-u8", 5));
    if (!quantized) {
        std::fprintf(stderr, "gen_golden: %s\n", quantized.error().message.c_str());
        return 1;
    }
    const ModelData tiny_u8 = std::move(quantized.value());
    const auto tiny_u8_bytes = bytes_of(serialize(tiny_u8));
    write(out / "valid" / "quantized_u8.lsnif", tiny_u8_bytes);
    // ... and an fp16 grid in a 1.1 header (grid_encoding 0): valid, although the reference
    // writer would have written it as 1.0. Pins that a 1.1 reader keeps the zero meaning.
    write(out / "valid" / "v1_1_fp16.lsnif", bytes_of(assemble(model_sections(tiny), 19, 1, 1)));

    // Version 1.2: ray inputs (the direction and the entry offsets: 3 + H more MLP inputs),
    // which the writer marks 1.2.
    ModelDesc tiny_dir_desc = tiny_desc();
    tiny_dir_desc.ray_inputs = kRayInputDirection | kRayInputEntryOffsets;
    const ModelData tiny_dir = make_model(tiny_dir_desc, "tiny-ray-inputs", 7);
    write(out / "valid" / "ray_inputs.lsnif", bytes_of(serialize(tiny_dir)));

    // ---- invalid: each breaks exactly one rule ------------------------------------------
    auto inv = [&](const char* name, std::vector<std::uint8_t> b) { write(out / "invalid" / name, b); };
    {
        std::vector<std::uint8_t> png = {0x89, 'P', 'N', 'G', 0x0D, 0x0A, 0x1A, 0x0A};
        png.resize(128, 0);
        inv("not_lsnif.lsnif", png);
    }
    {
        auto b = tiny_bytes;  // CR LF -> LF in the signature, as a text-mode FTP would do
        b.erase(b.begin() + 4);
        inv("text_mode_crlf.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[0] &= 0x7F;
        inv("seven_bit_transfer.lsnif", b);
    }
    inv("truncated_header.lsnif", {tiny_bytes.begin(), tiny_bytes.begin() + 40});
    inv("truncated_payload.lsnif", {tiny_bytes.begin(), tiny_bytes.end() - 70});
    {
        auto b = tiny_bytes;
        b.insert(b.end(), 16, 0);
        inv("trailing_bytes.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[8] = 2;  // major 2: no header checksum rewrite needed, versions are checked first
        inv("newer_major.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[8] = 0;
        inv("older_major.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[10] = 3;  // 1.3: one past the reference reader's 1.2
        reseal(b);
        inv("newer_minor.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[20] ^= 0x01;  // file_size changed without resealing
        inv("header_checksum.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[50] = 7;
        reseal(b);
        inv("header_reserved.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[kHeaderSize + 5] ^= 0x10;  // section 0 flags, table checksum left stale
        inv("table_checksum.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        put_u32(b, 32, 65);
        reseal(b);
        inv("too_many_sections.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        const std::size_t e = entry_of(b, kTagGrid);
        put_u64(b, e + 16, get_u64(b, entry_of(b, kTagOccupancy) + 16));  // GRID over OCCU
        reseal(b);
        inv("overlapping_sections.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        const std::size_t e = entry_of(b, kTagMlp);
        put_u64(b, e + 16, get_u64(b, e + 16) + 8);
        reseal(b);
        inv("misaligned_section.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        const std::size_t e = entry_of(b, kTagMeta);
        put_u64(b, e + 32, (std::uint64_t{1} << 30) + 1);
        reseal(b);
        inv("section_too_large.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        b[entry_of(b, kTagMlp) + 50] = 1;
        reseal(b);
        inv("entry_reserved.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        put_u32(b, entry_of(b, kTagMlp), make_tag("GRID"));
        reseal(b);
        inv("duplicate_tag.lsnif", b);
    }
    {
        auto secs = model_sections(tiny);
        secs.push_back({make_tag("NEXT"), LSNIF_SECTION_REQUIRED, {1, 2, 3}});
        inv("unknown_required_section.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        auto secs = model_sections(tiny);
        secs.erase(secs.begin() + 2);  // OCCU
        inv("missing_occupancy.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        auto b = tiny_bytes;
        const std::size_t e = entry_of(b, kTagMlp);
        b[get_u64(b, e + 16) + 3] ^= 0x40;  // payload bit flip, checksums stale
        inv("payload_checksum.lsnif", b);
    }
    {
        // An optional section of zero raw bytes whose stored bytes are a lone skippable frame
        // (RFC 8878 §3.1.2, magic 0x184D2A50, no content): zstd's streaming decoder reads it
        // as zero bytes, but it is not the one Zstandard frame FORMAT.md §4.4 asks for.
        WriteOptions raw;
        raw.zstd_level = 0;
        raw.extra_sections.push_back({make_tag("XTRA"), false, std::vector<std::uint8_t>(8, 0)});
        auto b = bytes_of(serialize(tiny, raw));
        const std::size_t e = entry_of(b, make_tag("XTRA"));
        const std::uint64_t off = get_u64(b, e + 16);
        const std::uint8_t skippable[8] = {0x50, 0x2A, 0x4D, 0x18, 0, 0, 0, 0};
        std::copy(skippable, skippable + 8, b.begin() + std::ptrdiff_t(off));
        put_u32(b, e + 8, LSNIF_COMPRESSION_ZSTD);
        put_u64(b, e + 32, 0);
        put_u32(b, e + 40, crc32c(b.data() + off, 8));
        put_u32(b, e + 44, 0);
        reseal(b);
        inv("skippable_frame.lsnif", b);
    }
    {
        auto b = tiny_bytes;  // corrupt zstd frame magic but keep checksums consistent
        const std::size_t e = entry_of(b, kTagMeta);
        const std::uint64_t off = get_u64(b, e + 16), size = get_u64(b, e + 24);
        b[off] ^= 0xFF;
        put_u32(b, e + 40, crc32c(b.data() + off, size));
        reseal(b);
        inv("zstd_garbage.lsnif", b);
    }
    {
        auto b = tiny_bytes;
        const std::size_t meta = entry_of(b, kTagMeta);
        const std::size_t pad = get_u64(b, meta + 16) + get_u64(b, meta + 24);  // first byte after META
        if (pad >= get_u64(b, entry_of(b, kTagModel) + 16)) {
            std::fprintf(stderr, "gen_golden: META payload leaves no padding\n");
            return 1;
        }
        b[pad] = 0xAA;
        inv("nonzero_padding.lsnif", b);
    }
    {
        ModelData m = tiny;  // GRID sized for another resolution than MODL declares
        auto secs = model_sections(m);
        ModelDesc other = tiny_desc();
        other.level_resolution = {3};  // (3+1)^3 = 64 dense entries instead of 256 hashed
        secs[1].raw = encode_descriptor(other);
        inv("grid_size_mismatch.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        auto secs = model_sections(tiny);
        secs[1].raw[60] = 0;  // hidden_width[0] = 0
        inv("zero_hidden_width.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        auto secs = model_sections(tiny);
        secs[1].raw[200] = 1;  // descriptor reserved area
        inv("descriptor_reserved.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        auto secs = model_sections(tiny);
        secs[1].raw[144] = 1;  // grid_encoding 1 in a 1.0 file: still reserved there
        inv("grid_encoding_in_v1_0.lsnif", bytes_of(assemble(secs, 19)));
    }
    // 1.1 descriptor and quantized GRID rules (FORMAT.md §6.2, §6.4.1, §7.2 E4.6a, E5, E10).
    auto inv_u8 = [&](const char* name, const std::vector<RawSection>& secs) {
        inv(name, bytes_of(assemble(secs, 0, 1, kMinorVersionQuantized)));
    };
    {
        auto secs = model_sections(tiny_u8);
        secs[1].raw[144] = 2;  // grid_encoding 2: not defined
        inv_u8("grid_encoding_unknown.lsnif", secs);
    }
    {
        auto secs = model_sections(tiny_u8);
        secs[1].raw[148] = 1;  // first byte still reserved in 1.1
        inv_u8("descriptor_reserved_v1_1.lsnif", secs);
    }
    {
        auto secs = model_sections(tiny_u8);
        secs[3].raw = model_sections(tiny)[3].raw;  // fp16-sized GRID under grid_encoding 1
        inv_u8("quantized_grid_size_mismatch.lsnif", secs);
    }
    // 1.2 descriptor rules (FORMAT.md §6.2, §7.2 E4.6b).
    auto inv_dir = [&](const char* name, const std::vector<RawSection>& secs) {
        inv(name, bytes_of(assemble(secs, 0, 1, kMinorVersionRayInputs)));
    };
    {
        auto secs = model_sections(tiny_dir);
        secs[1].raw[148] = 7;  // ray_inputs bit 2: not defined
        inv_dir("ray_inputs_unknown.lsnif", secs);
    }
    {
        auto secs = model_sections(tiny_dir);
        secs[1].raw[152] = 1;  // first byte still reserved in 1.2
        inv_dir("descriptor_reserved_v1_2.lsnif", secs);
    }
    {
        auto secs = model_sections(tiny);
        secs[1].raw[148] = 1;  // a direction input, but MLPW sized for the points' features only
        inv_dir("ray_inputs_weights_mismatch.lsnif", secs);
    }
    auto with_affine = [&](const char* name, float scale, float offset) {
        ModelData m = tiny_u8;
        m.grid_affine[0] = {scale, offset};
        inv_u8(name, model_sections(m));
    };
    with_affine("negative_scale.lsnif", -1e-6f, 0.0f);
    with_affine("nan_scale.lsnif", std::nanf(""), 0.0f);
    with_affine("inf_offset.lsnif", 1e-6f, INFINITY);
    with_affine("dequantized_overflow.lsnif", 1e37f, 3e38f);  // 255 * 1e37 + 3e38 > FLT_MAX
    {
        ModelData m = tiny;
        m.desc.box_max[1] = m.desc.box_min[1];  // flat box written without the writer's checks
        auto secs = model_sections(m);
        inv("empty_box.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        ModelData m = tiny;
        m.weights[1][3] = 0x7E00;  // NaN
        inv("nan_weight.lsnif", bytes_of(assemble(model_sections(m), 0)));
    }
    {
        ModelData m = tiny;
        m.grid[0][17] = 0x7C00;  // +Inf
        inv("inf_grid_feature.lsnif", bytes_of(assemble(model_sections(m), 0)));
    }
    {
        ModelDesc d3 = tiny_desc();
        d3.grid_resolution = 3;  // 27 bits: bits 27..31 of the last byte are unused
        ModelData m3 = make_model(d3, "v3", 4);
        m3.occupancy.back() |= 0x80;
        inv("occupancy_padding_bits.lsnif", bytes_of(assemble(model_sections(m3), 19)));
    }
    {
        auto secs = model_sections(tiny);
        secs[0].raw.assign({'{', 0, '}'});  // NUL inside the metadata
        inv("metadata_nul.lsnif", bytes_of(assemble(secs, 19)));
    }
    {
        ModelData m = tiny;
        m.metadata_json = "{\"format\": \"lsnif-metadata/1\", }";  // braces balanced, still not JSON
        inv("metadata_not_json.lsnif", bytes_of(serialize(m)));
        m.metadata_json = "{\"format\": \"lsnif-metadata/1\", ";  // truncated: the reader sees it
        inv("metadata_truncated.lsnif", bytes_of(assemble(model_sections(m), 19)));
    }
    {
        ModelData m = tiny;
        m.metadata_json =
            "{\"format\": \"lsnif-metadata/1\", \"tool\": {\"name\": \"x\", \"version\": \"1.0\"}}";
        inv("metadata_schema.lsnif", bytes_of(serialize(m)));
    }
    {
        ModelData m = tiny;
        ModelDesc wrong = tiny_desc();
        wrong.grid_resolution = 8;
        wrong.box_max[0] = 3.0f;
        m.metadata_json = metadata_for(wrong, "tiny");
        inv("metadata_disagrees.lsnif", bytes_of(serialize(m)));
    }
    return 0;
}
