// The cache glue of a conversion: keys, restoring a stored result, storing a new one
// (docs/pipeline.md "The cache"; convert_stages.hpp has the contracts).
#include <lsnif/cache/cache.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

namespace stages {

namespace {

// The gate's rules, for cache keys: they decide which option ships.
std::string gate_key(const Gate& g) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "gate%g,%g,%g,%g,%llu", g.min_visibility, g.min_family_visibility,
                  g.max_distance_median_pct, g.max_normal_median_deg, (unsigned long long)g.min_family_rays);
    return buf;
}

template <class T>
void hash_array(cache::Sha256& h, const std::vector<T>& v) {
    const std::uint64_t n = v.size();
    h.update({reinterpret_cast<const std::uint8_t*>(&n), sizeof n});
    h.update({reinterpret_cast<const std::uint8_t*>(v.data()), v.size() * sizeof(T)});
}

// Fields of a manifest entry that belong to the scene the mesh is in, not to its result.
constexpr const char* kSceneFields[] = {"id", "name", "input", "source_mesh", "instances"};

// Why a stored record cannot be restored; empty when it can. The entry's own checksum
// already caught damage: this catches an entry written by a tool that stored something else.
std::string record_problem(const json& record, const cache::Entry& entry) {
    if (!record.is_object() || !record.contains("class") || !record["class"].is_string())
        return "the record is not a mesh entry";
    if (record.contains("lsnif")) {
        const std::string file = record["lsnif"].value("file", "");
        if (file.empty() || file.find('/') != std::string::npos || file.find("..") != std::string::npos)
            return "the record names no usable asset file";
        if (entry.payload.empty()) return "the record names an asset but the entry holds none";
    }
    return {};
}

// A stored result as this scene's entry: its asset written into OUTDIR, the scene's own
// fields put back. False (and `error`) when the asset cannot be written.
bool restore_cached(const Run& run, Planned& p, json& record, const cache::Entry& entry, std::string& error) {
    if (record.contains("lsnif")) {
        error = write_asset(run, *p.mesh, entry.payload,
                            run.outdir / record["lsnif"]["file"].get<std::string>(), p.rec);
        if (!error.empty()) return false;
        record["lsnif"]["reused"] = true;
    }
    for (const char* f : kSceneFields) record[f] = p.rec.entry[f];
    // This run's own stages (classification, voxelization): the stored record has no timings.
    if (!p.rec.timings.empty()) record["timings"] = p.rec.timings;
    // The stored measurement, so that every run this entry serves reports the same bytes.
    if (record.contains("stats") && record["stats"].contains("bvh_bytes"))
        p.bvh_bytes = record["stats"]["bvh_bytes"].get<std::uint64_t>();
    return true;
}

// The entry to store for a result just converted: the record without the scene's fields and
// without what differs between runs (timings: strip_run_dependent), the asset's bytes as
// written. So an entry is a function of its key: every machine and thread count stores the
// same bytes. Empty record when the asset cannot be read back.
cache::Entry entry_to_store(const Run& run, const json& result, std::string& problem) {
    cache::Entry entry;
    json record = result;
    for (const char* f : kSceneFields) record.erase(f);
    strip_run_dependent(record);
    if (record.contains("lsnif")) {
        auto bytes =
            format::read_file_bytes((run.outdir / record["lsnif"]["file"].get<std::string>()).string());
        if (!bytes) {
            problem = bytes.error().message;
            return {};
        }
        entry.payload = std::move(*bytes);
    }
    entry.record = record.dump();
    return entry;
}

}  // namespace

const std::string& cache_key(const Run& run, Planned& p) {
    static_assert(std::endian::native == std::endian::little, "cache keys hash little-endian arrays");
    if (!p.key.empty()) return p.key;
    const scene::Mesh& m = *p.mesh;
    cache::Sha256 h;
    h.update("lsnif-convert-result/2\n").update(tool_identity().digest).update("\n");
    h.update(asset_key(run, m, p.candidate->desc))
        .update("\n")
        .update(gate_key(run.preset.gate))
        .update("\n");
    h.update(p.forced() ? "forced\n" : "automatic\n")
        .update(p.source)
        .update("\n")
        .update(m.name)
        .update("\n");
    hash_array(h, m.positions);
    hash_array(h, m.indices);
    hash_array(h, m.normals);
    hash_array(h, m.triangle_materials);
    p.key = h.hex();
    return p.key;
}

json convert_cached(const Run& run, Planned& p, std::vector<std::string>& errors,
                    std::vector<std::string>& warnings, CacheCounts& counts) {
    if (!run.cache || run.opt.dry_run) return convert_candidate(run, p, errors);
    const std::string& key = cache_key(run, p);
    const cache::Lookup found = run.cache->get(key);
    if (found.status == cache::Status::corrupt) {
        ++counts.corrupt;
        warnings.push_back("corrupt cache entry, converting again: " + found.problem);
    } else if (found.status == cache::Status::hit) {
        json record = json::parse(found.entry.record, nullptr, false);
        std::string why = record_problem(record, found.entry);
        if (why.empty()) {
            if (!restore_cached(run, p, record, found.entry, why)) {
                errors.push_back(p.source + ": mesh '" + p.mesh->name + "': " + why);
                return p.rec.failed("the asset could not be written: " + why);
            }
            ++counts.hits;
            return record;
        }
        ++counts.corrupt;
        warnings.push_back("unusable cache entry, converting again: " + run.cache->entry_path(key).string() +
                           ": " + why);
    }
    const std::size_t errors_before = errors.size();
    json result = convert_candidate(run, p, errors);
    if (errors.size() != errors_before) return result;  // a failed write is not a result to keep
    std::string problem;
    const cache::Entry entry = entry_to_store(run, result, problem);
    auto stored = problem.empty() ? run.cache->put(key, entry) : cache::Result<void>(cache::Error{problem});
    if (!stored)
        warnings.push_back("not cached: " + stored.error().message);
    else
        ++counts.stored;
    return result;
}

void strip_run_dependent(json& entry) {
    entry.erase("timings");
    if (entry.contains("lsnif")) entry["lsnif"].erase("reused");
    if (entry.contains("candidates"))
        for (json& c : entry["candidates"]) c.erase("seconds");
}

}  // namespace stages

}  // namespace lsnif::converter
