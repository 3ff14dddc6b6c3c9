// `lsnif merge` (batch.hpp): the output directories of a sharded `lsnif batch` joined into
// one library, after checking that they are one complete set of the same conversion.
#include <lsnif/converter/manifest.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/library/batch.hpp>

#include <filesystem>
#include <fstream>
#include <set>
#include <string>
#include <vector>

namespace lsnif::library {

namespace fs = std::filesystem;
using converter::InputRecord;
using converter::MeshOutcome;
using converter::OutcomeFields;
using nlohmann::json;

nlohmann::json merge_summary_json(const std::vector<std::string>& shard_dirs, const std::string& outdir,
                                  const MergeResult& merged) {
    nlohmann::json j = {{"shards", shard_dirs}, {"output", outdir}, {"errors", merged.errors}};
    if (merged.errors.empty()) {
        j["manifest"] = outdir + "/manifest.json";
        j["meshes"] = merged.meshes.size();
        j["scene_memory"] = converter::scene_memory_json(merged.memory);
    }
    return j;
}

std::string merge_junit_xml(const MergeResult& merged) {
    BatchResult r;
    r.convert.inputs = merged.inputs;
    r.convert.meshes = merged.meshes;
    return junit_xml(r);
}

namespace {

// A shard's manifest, read and checked for the shard record merge needs; its inputs and
// meshes typed (a batch manifest is reproducible: no timings).
struct ShardManifest {
    fs::path dir;
    json doc;
    std::uint32_t index = 0, count = 0;
    std::vector<InputRecord> inputs;
    std::vector<MeshOutcome> meshes;
    converter::SceneMemory memory;  // the shard's own scene_memory: its settings' yardstick and budget
};

std::string read_shard(const fs::path& dir, ShardManifest& out) {
    const fs::path path = dir / "manifest.json";
    const std::string where = path.string() + ": ";
    std::ifstream f(path);
    if (!f) return where + "cannot read (not an lsnif batch output directory?)";
    out.dir = dir;
    out.doc = json::parse(f, nullptr, false);
    const json& doc = out.doc;
    if (!doc.is_object() || doc.value("format", json()) != converter::kManifestFormat ||
        !doc.contains("meshes") || !doc["meshes"].is_array() || !doc.contains("inputs") ||
        !doc["inputs"].is_array())
        return where + "not an lsnif manifest of format " + converter::kManifestFormat;
    const json& shard = doc.value("shard", json());
    if (!shard.is_object() || !shard.value("index", json()).is_number_unsigned() ||
        !shard.value("count", json()).is_number_unsigned())
        return where + "not written by lsnif batch --shard";
    out.index = shard["index"].get<std::uint32_t>();
    out.count = shard["count"].get<std::uint32_t>();
    for (std::size_t i = 0; i < doc["inputs"].size(); ++i) {
        auto in = converter::input_from_json(doc["inputs"][i]);
        if (!in) return where + "inputs[" + std::to_string(i) + "]." + in.error();
        out.inputs.push_back(std::move(*in));
    }
    for (std::size_t i = 0; i < doc["meshes"].size(); ++i) {
        auto m = converter::outcome_from_json(doc["meshes"][i], OutcomeFields::reproducible);
        if (!m) return where + "meshes[" + std::to_string(i) + "]." + m.error();
        if (m->input >= out.inputs.size())
            return where + "meshes[" + std::to_string(i) + "].input: no such input";
        if (!m->memory) return where + "meshes[" + std::to_string(i) + "].memory: missing";
        out.meshes.push_back(std::move(*m));
    }
    auto memory = converter::scene_memory_from_json(doc.value("scene_memory", json()));
    if (!memory) return where + "scene_memory." + memory.error();
    out.memory = *memory;
    return {};
}

// "tool.version is 0.2.0 where DIR's is 0.1.0": the first field of object `key` in which
// the two documents differ (a field one of them lacks reads as null).
std::string field_difference(const char* key, const json& a, const json& b, const fs::path& a_dir) {
    const json &oa = a.value(key, json::object()), &ob = b.value(key, json::object());
    std::set<std::string> fields;
    for (const json* o : {&oa, &ob})
        if (o->is_object())
            for (const auto& [k, v] : o->items()) fields.insert(k);
    for (const std::string& f : fields) {
        const json va = oa.is_object() ? oa.value(f, json()) : json(),
                   vb = ob.is_object() ? ob.value(f, json()) : json();
        if (va != vb)
            return std::string(key) + "." + f + " is " + vb.dump() + " where " + a_dir.string() + "'s is " +
                   va.dump();
    }
    return std::string("its ") + key + " differ from " + a_dir.string() + "'s";
}

// Why shard `b` does not describe the same conversion as shard `a`; empty when it does. The
// thread count and the CPU never differ between shards' results (canonical arithmetic), so
// shards from any machine join; another tool, another arithmetic or other settings do not.
std::string shard_mismatch(const ShardManifest& a, const ShardManifest& b) {
    for (const char* k : {"tool", "settings"})
        if (a.doc.value(k, json()) != b.doc.value(k, json())) return field_difference(k, a.doc, b.doc, a.dir);
    if (a.doc.value("instances", json()) != b.doc.value("instances", json()))
        return "its instances differ from " + a.dir.string() + "'s";
    if (a.meshes.size() != b.meshes.size() || a.inputs.size() != b.inputs.size())
        return "its inputs or meshes differ from " + a.dir.string() + "'s";
    for (std::size_t i = 0; i < a.inputs.size(); ++i)
        if (a.inputs[i].given != b.inputs[i].given) return "its inputs differ from " + a.dir.string() + "'s";
    for (std::size_t i = 0; i < a.meshes.size(); ++i) {
        const MeshOutcome &x = a.meshes[i], &y = b.meshes[i];
        const char* differs = x.name != y.name                     ? "name"
                              : x.geometry_hash != y.geometry_hash ? "geometry_hash"
                              : x.input != y.input                 ? "input"
                              : x.source_mesh != y.source_mesh     ? "source_mesh"
                              : x.shard != y.shard                 ? "shard"
                                                                   : nullptr;
        if (differs)
            return "mesh " + std::to_string(i) + " differs from " + a.dir.string() + "'s (" + differs + ")";
    }
    return {};
}

// The shards in index order, or errors when they are not a complete, consistent set.
std::vector<const ShardManifest*> shard_set(const std::vector<ShardManifest>& shards,
                                            std::vector<std::string>& errors) {
    std::vector<const ShardManifest*> by_index(shards.size() + 1, nullptr);
    for (const ShardManifest& s : shards) {
        if (s.count != shards.size() || s.index < 1 || s.index > s.count || by_index[s.index]) {
            errors.push_back((s.dir / "manifest.json").string() + ": shard " + std::to_string(s.index) + "/" +
                             std::to_string(s.count) + " does not complete a set of " +
                             std::to_string(shards.size()) + " shards, each given once");
            continue;
        }
        by_index[s.index] = &s;
        if (std::string why = shard_mismatch(shards[0], s); !why.empty())
            errors.push_back((s.dir / "manifest.json").string() + ": " + why);
    }
    return by_index;
}

// Mesh `i` from the shard that converted it, its asset copied into `outdir`.
MeshOutcome take_mesh(const std::vector<const ShardManifest*>& by_index, const ShardManifest& first,
                      std::size_t i, const std::string& outdir, std::vector<std::string>& errors) {
    const MeshOutcome& here = first.meshes[i];
    if (!here.shard) return here;
    const ShardManifest& owner = *by_index.at(*here.shard);
    MeshOutcome m = owner.meshes[i];
    m.shard.reset();
    if (m.asset) {
        auto bytes = format::read_file_bytes((owner.dir / m.asset->file).string());
        if (!bytes)
            errors.push_back(bytes.error().message);
        else if (const format::Error e =
                     format::write_bytes_atomically((fs::path(outdir) / m.asset->file).string(), *bytes))
            errors.push_back(e.message);
    }
    return m;
}

}  // namespace

MergeResult merge(const std::vector<std::string>& shard_dirs, const std::string& outdir) {
    MergeResult r;
    std::vector<ShardManifest> shards(shard_dirs.size());
    for (std::size_t k = 0; k < shard_dirs.size(); ++k)
        if (std::string e = read_shard(shard_dirs[k], shards[k]); !e.empty()) r.errors.push_back(e);
    if (!r.errors.empty()) return r;
    const std::vector<const ShardManifest*> by_index = shard_set(shards, r.errors);
    if (!r.errors.empty()) return r;

    std::error_code ec;
    fs::create_directories(outdir, ec);  // assets are copied in as their entries are taken
    const ShardManifest& first = shards[0];
    for (std::size_t i = 0; i < first.meshes.size(); ++i)
        r.meshes.push_back(take_mesh(by_index, first, i, outdir, r.errors));
    r.inputs = first.inputs;
    for (InputRecord& in : r.inputs) {
        fs::path p = in.path;
        if (p.is_relative()) p = first.dir / p;
        in.path = converter::manifest_relative_path(p, outdir);
    }
    if (!r.errors.empty()) return r;
    json merged = first.doc;
    merged.erase("shard");
    merged["inputs"] = json::array();
    for (const InputRecord& in : r.inputs) merged["inputs"].push_back(converter::input_json(in));
    merged["meshes"] = json::array();
    for (const MeshOutcome& m : r.meshes)
        merged["meshes"].push_back(converter::outcome_json(m, OutcomeFields::reproducible));
    // The shards' meshes were measured on the settings' yardstick and budget, which every
    // shard records alike (shard_mismatch); the sums are the whole library's again.
    r.memory = converter::scene_memory(r.meshes, first.memory.yardstick, first.memory.budget.value_or(0),
                                       first.memory.estimated);
    merged["scene_memory"] = converter::scene_memory_json(r.memory);
    if (std::string e = converter::write_manifest(outdir, merged); !e.empty()) r.errors.push_back(e);
    return r;
}

}  // namespace lsnif::library
