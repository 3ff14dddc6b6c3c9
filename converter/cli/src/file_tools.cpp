#include <lsnif/lsnif.h>
#include <lsnif/cli/file_tools.hpp>
#include <lsnif/converter/json_schema.hpp>
#include <lsnif/converter/metadata_names.hpp>

#include <algorithm>
#include <cinttypes>
#include <cstdio>
#include <fstream>
#include <memory>
#include <sstream>

namespace lsnif::cli {

using converter::distance_encoding_name;
using converter::grid_encoding_name;
using converter::ray_inputs_name;
using converter::SchemaViolation;
using nlohmann::json;

namespace {

struct ModelCloser {
    void operator()(lsnif_model* m) const { lsnif_close(m); }
};
using ModelPtr = std::unique_ptr<lsnif_model, ModelCloser>;

Problem problem_from(const lsnif_error& e) {
    return {lsnif_status_string(e.status), e.offset, e.message};
}

GridInfo grid_info(const lsnif_model* model, const lsnif_info& info) {
    GridInfo g{grid_encoding_name(info.grid_encoding), info.grid_encoding == LSNIF_GRID_U8_AFFINE, {}};
    if (!g.quantized) return g;
    for (std::uint32_t l = 0; l < info.level_count; ++l) {
        lsnif_array a{};
        if (lsnif_get_array(model, LSNIF_ARRAY_GRID_DEQUANT, l, &a) != LSNIF_OK) break;
        const float* p = static_cast<const float*>(a.data);
        g.levels.push_back({p[0], p[1]});
    }
    return g;
}

std::string grid_text(const GridInfo& g) {
    std::string out = g.encoding;
    if (!g.quantized) return out;
    for (std::size_t l = 0; l < g.levels.size(); ++l) {
        char buf[96];
        // %.9g round-trips a float exactly.
        std::snprintf(buf, sizeof buf, "%s level %zu scale %.9g offset %.9g", l ? ";" : ":", l,
                      double(g.levels[l].scale), double(g.levels[l].offset));
        out += buf;
    }
    return out;
}

std::uint32_t ray_inputs_of(const lsnif_model* model) {
    std::uint32_t bits = 0;
    lsnif_get_ray_inputs(model, &bits);
    return bits;
}

double occupied_fraction(const lsnif_info& info) {
    const double v = info.grid_resolution;
    return double(info.occupied_voxels) / (v * v * v);
}

const char* compression_name(const lsnif_section_info& s) {
    return s.compression == LSNIF_COMPRESSION_ZSTD ? "zstd" : "none";
}

const char* checksum_name(const lsnif_section_info& s) {
    return s.checksum_ok ? "ok" : "mismatch";
}

const char* indexing_name(const lsnif_info& info, std::uint32_t level) {
    return info.level_dense[level] ? "dense" : "hashed";
}

double compression_ratio(const lsnif_section_info& s) {
    return s.stored_size ? double(s.raw_size) / double(s.stored_size) : 1.0;
}

json model_json(const InspectModel& m) {
    const lsnif_info& info = m.info;
    json levels = json::array();
    for (std::uint32_t l = 0; l < info.level_count; ++l)
        levels.push_back({{"resolution", info.level_resolution[l]},
                          {"entries", info.level_entries[l]},
                          {"indexing", indexing_name(info, l)}});
    json hidden = json::array();
    for (std::uint32_t k = 0; k < info.hidden_layer_count; ++k) hidden.push_back(info.hidden_width[k]);
    return {{"grid_resolution", info.grid_resolution},
            {"occupied_voxels", info.occupied_voxels},
            {"occupied_fraction", occupied_fraction(info)},
            {"max_points", info.max_points},
            {"features_per_level", info.features_per_level},
            {"log2_table_size", info.log2_table_size},
            {"levels", levels},
            {"hash_primes", {info.hash_primes[0], info.hash_primes[1], info.hash_primes[2]}},
            {"input_width", info.input_width},
            {"ray_inputs", ray_inputs_name(m.ray_inputs)},
            {"hidden_widths", hidden},
            {"grid", grid_info_json(m.grid)},
            {"output_count", info.output_count},
            {"material_count", info.material_count},
            {"activation", "relu"},
            {"distance_encoding", distance_encoding_name(info.distance_encoding)},
            {"box_min", {info.box_min[0], info.box_min[1], info.box_min[2]}},
            {"box_max", {info.box_max[0], info.box_max[1], info.box_max[2]}},
            {"parameter_count", info.parameter_count},
            {"decoded_bytes", info.decoded_bytes}};
}

// Leaves `model` in fp32.
InspectMemory memory_of(lsnif_model* model, const lsnif_info& opened) {
    const lsnif_arithmetic chosen = lsnif_get_arithmetic(model);
    lsnif_info fp32{};
    if (lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, nullptr) != LSNIF_OK ||
        lsnif_get_info(model, &fp32) != LSNIF_OK)
        fp32 = opened;
    return {opened.file_size, opened.decoded_bytes, fp32.decoded_bytes, lsnif_arithmetic_string(chosen)};
}

json memory_json(const InspectMemory& m) {
    return {{"file_bytes", m.file_bytes},
            {"resident_bytes", m.resident_bytes},
            {"arithmetic", m.arithmetic},
            {"resident_bytes_fp32", m.resident_bytes_fp32}};
}

json section_json(const lsnif_section_info& s) {
    return {{"tag", s.tag},
            {"known", bool(s.known)},
            {"required", bool(s.flags & LSNIF_SECTION_REQUIRED)},
            {"compression", compression_name(s)},
            {"offset", s.offset},
            {"stored_size", s.stored_size},
            {"raw_size", s.raw_size},
            {"compression_ratio", compression_ratio(s)},
            {"stored_crc32c", s.stored_crc32c},
            {"raw_crc32c", s.raw_crc32c},
            {"checksum", checksum_name(s)}};
}

std::string version_of(const lsnif_header_info& h) {
    return std::to_string(h.version_major) + "." + std::to_string(h.version_minor);
}

std::string fmt_bytes(std::uint64_t n) {
    char buf[64];
    if (n < 10 * 1024)
        std::snprintf(buf, sizeof buf, "%" PRIu64 " B", n);
    else if (n < 10 * 1024 * 1024)
        std::snprintf(buf, sizeof buf, "%.1f KiB", double(n) / 1024);
    else
        std::snprintf(buf, sizeof buf, "%.1f MiB", double(n) / (1024 * 1024));
    return buf;
}

}  // namespace

json grid_info_json(const GridInfo& grid) {
    json g = {{"encoding", grid.encoding}};
    if (!grid.quantized) return g;
    json levels = json::array();
    for (const GridDequant& l : grid.levels) levels.push_back({{"scale", l.scale}, {"offset", l.offset}});
    g["levels"] = levels;
    return g;
}

std::vector<std::string> metadata_consistency(const json& meta, const lsnif_info& info,
                                              std::uint32_t ray_inputs) {
    std::vector<std::string> out;
    if (!meta.is_object()) return out;
    auto check = [&](const std::string& name, const json& got, const json& want) {
        if (got != want)
            out.push_back("metadata " + name + " is " + got.dump() + " but the model descriptor says " +
                          want.dump());
    };
    if (auto m = meta.find("model"); m != meta.end() && m->is_object()) {
        json levels = json::array(), hidden = json::array();
        for (std::uint32_t l = 0; l < info.level_count; ++l) levels.push_back(info.level_resolution[l]);
        for (std::uint32_t k = 0; k < info.hidden_layer_count; ++k) hidden.push_back(info.hidden_width[k]);
        const std::pair<const char*, json> fields[] = {
            {"grid_resolution", info.grid_resolution},
            {"max_points", info.max_points},
            {"level_resolutions", levels},
            {"features_per_level", info.features_per_level},
            {"log2_table_size", info.log2_table_size},
            {"hidden_widths", hidden},
            {"output_count", info.output_count},
            {"material_count", info.material_count},
            {"activation", "relu"},
            {"distance_encoding", distance_encoding_name(info.distance_encoding)},
            {"grid_encoding", grid_encoding_name(info.grid_encoding)},
            {"ray_inputs", ray_inputs_name(ray_inputs)},
            {"parameter_count", info.parameter_count}};
        for (const auto& [key, want] : fields)
            if (m->contains(key)) check(std::string("model.") + key, (*m)[key], want);
    }
    if (auto o = meta.find("object"); o != meta.end() && o->is_object()) {
        for (const char* key : {"box_min", "box_max"}) {
            if (!o->contains(key) || !(*o)[key].is_array() || (*o)[key].size() != 3) continue;
            const float* want = key[4] == 'm' && key[5] == 'i' ? info.box_min : info.box_max;
            for (int i = 0; i < 3; ++i) {
                const json& v = (*o)[key][i];
                // The descriptor stores f32; the JSON must round-trip to the same float.
                if (!v.is_number() || float(v.get<double>()) != want[i]) {
                    check(std::string("object.") + key, (*o)[key], json{want[0], want[1], want[2]});
                    break;
                }
            }
        }
    }
    return out;
}

ValidationReport validate_bytes(std::span<const std::uint8_t> bytes, const std::string& name) {
    ValidationReport r{name, {}, {}, {}};
    lsnif_error err{};
    lsnif_header_info header{};
    std::vector<lsnif_section_info> sections(64);
    std::uint32_t count = 0;
    const lsnif_status scan_status = lsnif_scan_memory(bytes.data(), bytes.size(), &header, sections.data(),
                                                       std::uint32_t(sections.size()), &count, &err);
    if (scan_status != LSNIF_OK) {
        if (scan_status == LSNIF_ERR_CHECKSUM || scan_status == LSNIF_ERR_DECOMPRESS) {
            // The table parsed: report every damaged section, one line each.
            for (std::uint32_t i = 0; i < count && i < sections.size(); ++i)
                if (!sections[i].checksum_ok)
                    r.problems.push_back(
                        {lsnif_status_string(lsnif_status(sections[i].payload_status)), sections[i].offset,
                         std::string("section '") + sections[i].tag + "' payload is damaged (" +
                             (sections[i].payload_status == LSNIF_ERR_DECOMPRESS ? "zstd data does not decode"
                              : sections[i].decoded ? "uncompressed checksum mismatch"
                                                    : "stored-bytes checksum mismatch") +
                             ")"});
            if (r.problems.empty()) r.problems.push_back(problem_from(err));
        } else {
            r.problems.push_back(problem_from(err));
        }
        return r;
    }
    lsnif_model* raw = nullptr;
    if (lsnif_open_memory(bytes.data(), bytes.size(), &raw, &err) != LSNIF_OK) {
        r.problems.push_back(problem_from(err));
        return r;
    }
    ModelPtr model(raw);
    lsnif_info info{};
    lsnif_get_info(model.get(), &info);
    r.version = std::to_string(info.version_major) + "." + std::to_string(info.version_minor);
    r.grid = grid_info(model.get(), info);
    std::size_t len = 0;
    const char* text = lsnif_metadata(model.get(), &len);
    json meta;
    try {
        meta = json::parse(text, text + len);
    } catch (const json::parse_error& e) {
        r.problems.push_back(
            {"metadata", UINT64_MAX, std::string("metadata is not valid JSON: ") + e.what()});
        return r;
    }
    for (const SchemaViolation& v : converter::metadata_schema().validate(meta))
        r.problems.push_back(
            {"metadata", UINT64_MAX,
             "metadata " + (v.pointer.empty() ? std::string("(root)") : v.pointer) + " " + v.message});
    for (const std::string& m : metadata_consistency(meta, info, ray_inputs_of(model.get())))
        r.problems.push_back({"metadata", UINT64_MAX, m});
    return r;
}

ValidationReport validate_file(const std::string& path) {
    std::ifstream f(path, std::ios::binary);
    if (!f) return {path, {{lsnif_status_string(LSNIF_ERR_IO), UINT64_MAX, "cannot open the file"}}, {}, {}};
    std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
    if (f.bad()) return {path, {{lsnif_status_string(LSNIF_ERR_IO), UINT64_MAX, "read error"}}, {}, {}};
    return validate_bytes(bytes, path);
}

json ValidationReport::to_json() const {
    json probs = json::array();
    for (const Problem& p : problems) {
        json j = {{"status", p.status}, {"message", p.message}};
        if (p.offset != UINT64_MAX) j["offset"] = p.offset;
        probs.push_back(j);
    }
    json j = {{"path", path}, {"valid", valid()}, {"problems", probs}};
    if (!version.empty()) j["version"] = version;
    if (grid) j["grid"] = grid_info_json(*grid);
    return j;
}

std::string ValidationReport::to_text() const {
    if (valid()) {
        // The verdict line stays "PATH: ok" (scripts match it); a quantized grid adds one
        // indented line with its dequantization pairs.
        if (grid && grid->quantized)
            return path + ": ok\n  format " + version + ", grid " + grid_text(*grid) + "\n";
        return path + ": ok\n";
    }
    std::string out;
    for (const Problem& p : problems) {
        out += path + ": error: " + p.message;
        if (p.offset != UINT64_MAX) out += " (at byte " + std::to_string(p.offset) + ")";
        out += "\n";
    }
    return out;
}

InspectReport inspect_bytes(std::span<const std::uint8_t> bytes, const std::string& name) {
    InspectReport r;
    r.path = name;
    r.file_size = bytes.size();
    lsnif_error err{};
    lsnif_header_info header{};
    std::vector<lsnif_section_info> sections(64);
    std::uint32_t count = 0;
    const lsnif_status st = lsnif_scan_memory(bytes.data(), bytes.size(), &header, sections.data(),
                                              std::uint32_t(sections.size()), &count, &err);
    if (count > 0 || st == LSNIF_OK) {
        r.header = header;
        sections.resize(std::min<std::size_t>(count, sections.size()));
        r.sections = std::move(sections);
    }
    if (st != LSNIF_OK) {
        r.error = problem_from(err);
        return r;
    }
    lsnif_model* raw = nullptr;
    if (lsnif_open_memory(bytes.data(), bytes.size(), &raw, &err) != LSNIF_OK) {
        r.error = problem_from(err);
        return r;
    }
    ModelPtr model(raw);
    lsnif_info info{};
    lsnif_get_info(model.get(), &info);
    r.model = InspectModel{info, ray_inputs_of(model.get()), grid_info(model.get(), info)};
    r.memory = memory_of(model.get(), info);
    std::size_t len = 0;
    const char* text = lsnif_metadata(model.get(), &len);
    r.metadata_text.assign(text, len);
    try {
        r.metadata = json::parse(r.metadata_text);
    } catch (const json::parse_error&) {
    }
    return r;
}

json inspect_json(const InspectReport& r) {
    json j = {{"path", r.path}, {"file_size", r.file_size}};
    if (r.header) {
        j["header"] = {{"version", version_of(*r.header)},
                       {"file_size", r.header->file_size},
                       {"table_offset", r.header->table_offset},
                       {"section_count", r.header->section_count}};
        json secs = json::array();
        for (const lsnif_section_info& s : r.sections) secs.push_back(section_json(s));
        j["sections"] = secs;
    }
    if (r.error) j["error"] = {{"status", r.error->status}, {"message", r.error->message}};
    if (r.model) j["model"] = model_json(*r.model);
    if (r.memory) j["memory"] = memory_json(*r.memory);
    if (r.metadata)
        j["metadata"] = *r.metadata;
    else if (r.model)
        j["metadata_text"] = r.metadata_text;
    return j;
}

std::string inspect_text(const InspectReport& r) {
    std::ostringstream o;
    o << r.path << "\n";
    if (r.header) {
        const lsnif_header_info& h = *r.header;
        o << "  format version " << version_of(h) << ", " << fmt_bytes(h.file_size) << ", " << h.section_count
          << " sections (table at byte " << h.table_offset << ")\n";
        o << "  tag   req  codec  offset      stored       raw  ratio  checksum\n";
        for (const lsnif_section_info& s : r.sections) {
            char line[256];
            std::snprintf(line, sizeof line, "  %-4s  %-3s  %-5s  %6" PRIu64 "  %10s  %10s  %5.2f  %s%s\n",
                          s.tag, s.flags & LSNIF_SECTION_REQUIRED ? "yes" : "no", compression_name(s),
                          std::uint64_t(s.offset), fmt_bytes(s.stored_size).c_str(),
                          fmt_bytes(s.raw_size).c_str(), compression_ratio(s), checksum_name(s),
                          s.known ? "" : "  (unknown, skipped)");
            o << line;
        }
    }
    if (r.error) o << "  error: " << r.error->message << "\n";
    if (r.model) {
        const lsnif_info& m = r.model->info;
        o << "  model: V=" << m.grid_resolution << " (" << m.occupied_voxels << " occupied, " << std::fixed;
        o.precision(1);
        o << 100.0 * occupied_fraction(m) << "%), H=" << m.max_points << ", F=" << m.features_per_level
          << ", T=2^" << m.log2_table_size << ", levels";
        for (std::uint32_t l = 0; l < m.level_count; ++l)
            o << " " << m.level_resolution[l] << "(" << indexing_name(m, l) << ")";
        o << "\n  mlp: " << m.input_width;
        if (const std::string inputs = ray_inputs_name(r.model->ray_inputs); inputs != "none")
            o << " (ray inputs: " << inputs << ")";
        for (std::uint32_t k = 0; k < m.hidden_layer_count; ++k) o << " -> " << m.hidden_width[k];
        o << " -> " << m.output_count << " (ReLU), distance " << distance_encoding_name(m.distance_encoding)
          << "\n";
        o << "  grid: " << grid_text(r.model->grid) << "\n";
        o.precision(6);
        // The box as JSON writes it: the same shortest round-trip digits as --json.
        const json box_min = {m.box_min[0], m.box_min[1], m.box_min[2]};
        const json box_max = {m.box_max[0], m.box_max[1], m.box_max[2]};
        o << std::defaultfloat << "  box: " << box_min.dump() << " .. " << box_max.dump() << "\n";
        o << "  parameters: " << m.parameter_count << "\n";
    }
    if (r.memory) {
        const InspectMemory& m = *r.memory;
        o << "  memory: " << fmt_bytes(m.resident_bytes) << " held once open (" << m.arithmetic
          << " network on this CPU; " << fmt_bytes(m.resident_bytes_fp32)
          << " with the fp32 network, on any CPU), " << fmt_bytes(m.file_bytes) << " in the file\n";
    }
    if (r.metadata)
        o << "  metadata: " << r.metadata->dump(2) << "\n";
    else if (r.model)
        o << "  metadata (not JSON): " << r.metadata_text << "\n";
    return o.str();
}

}  // namespace lsnif::cli
