// The cache glue of a conversion: keys, restoring a stored result, storing a new one
// (docs/pipeline.md "The cache"; convert_stages.hpp has the contracts).
#include <lsnif/cache/remote.hpp>
#include <lsnif/converter/settings.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

namespace stages {

namespace {

// The gate's rules, for cache keys: they decide which option ships.
std::string gate_key(const Gate& g) {
    char buf[200];
    std::snprintf(buf, sizeof buf, "gate%g,%g,%g,%g,%llu,%g,%s", g.min_visibility, g.min_family_visibility,
                  g.max_distance_median_pct, g.max_normal_median_deg, (unsigned long long)g.min_family_rays,
                  g.max_flip, acceptance_name(g.accept));
    return buf;
}

template <class T>
void hash_array(cache::Sha256& h, const std::vector<T>& v) {
    const std::uint64_t n = v.size();
    h.update({reinterpret_cast<const std::uint8_t*>(&n), sizeof n});
    h.update({reinterpret_cast<const std::uint8_t*>(v.data()), v.size() * sizeof(T)});
}

// A stored record as an outcome, or why it cannot be restored. The entry's own checksum
// already caught damage: this catches an entry written by a tool that stored something else.
base::Result<MeshOutcome, std::string> stored_outcome(const cache::Entry& entry) {
    const json record = json::parse(entry.record, nullptr, false);
    auto o = outcome_from_json(record, OutcomeFields::result);
    if (!o) return "the record is not a mesh outcome: " + o.error();
    if (o->asset && entry.payload.empty())
        return std::string("the record names an asset but the entry holds none");
    return o;
}

// A stored result as this scene's outcome: its asset written into OUTDIR, where the mesh is
// in this scene and this run's own stages (classification, voxelization) put back. False
// (and `error`) when the asset cannot be written.
bool restore_cached(const Run& run, Triaged& p, MeshOutcome stored, const cache::Entry& entry,
                    std::string& error) {
    if (stored.asset) {
        error = write_asset(run, *p.mesh, entry.payload, run.outdir / stored.asset->file, p.out);
        if (!error.empty()) return false;
        stored.asset->reused = true;
    }
    keep_scene_place(stored, p.out);
    // The stored measurement, so that every run this entry serves reports the same bytes.
    if (stored.stats) p.bvh_bytes = stored.stats->bvh.of(run.preset.classify.yardstick);
    p.out = std::move(stored);
    return true;
}

// The entry to store for a result just converted: the outcome without where the mesh is in
// its scene and without what differs between runs (OutcomeFields::result), the asset's bytes
// as written. So an entry is a function of its key: every machine and thread count stores the
// same bytes. False (and `problem`) when the asset cannot be read back.
bool entry_to_store(const Run& run, const MeshOutcome& result, cache::Entry& entry, std::string& problem) {
    if (result.asset) {
        auto bytes = format::read_file_bytes((run.outdir / result.asset->file).string());
        if (!bytes) {
            problem = bytes.error().message;
            return false;
        }
        entry.payload = std::move(*bytes);
    }
    entry.record = outcome_json(result, OutcomeFields::result).dump();
    return true;
}

}  // namespace

const std::string& cache_key(const Run& run, Triaged& p) {
    static_assert(std::endian::native == std::endian::little, "cache keys hash little-endian arrays");
    if (!p.key.empty()) return p.key;
    const scene::Mesh& m = *p.mesh;
    cache::Sha256 h;
    h.update("lsnif-convert-result/4\n").update(tool_identity().digest).update("\n");
    h.update(asset_key(run, m, p.candidate->desc))
        .update("\n")
        .update(gate_key(run.preset.gate))
        .update("\n")
        .update(report_settings_key(run.opt))
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

void convert_cached(const Run& run, Triaged& p, std::vector<std::string>& errors,
                    std::vector<std::string>& warnings, CacheCounts& counts) {
    if (!run.cache || run.opt.dry_run) return convert_candidate(run, p, errors);
    const std::string& key = cache_key(run, p);
    const cache::Lookup found = run.cache->get(key);
    for (std::string& w : run.cache->take_warnings()) warnings.push_back(std::move(w));
    if (found.status == cache::Status::corrupt) {
        ++counts.corrupt;
        warnings.push_back("corrupt cache entry, converting again: " + found.problem);
    } else if (found.status == cache::Status::hit) {
        auto stored = stored_outcome(found.entry);
        if (stored) {
            std::string why;
            if (!restore_cached(run, p, std::move(*stored), found.entry, why)) {
                errors.push_back(p.source + ": mesh '" + p.mesh->name + "': " + why);
                p.out.settle(Decision::write_failed, "the asset could not be written: " + why);
                return;
            }
            ++counts.hits;
            return;
        }
        ++counts.corrupt;
        warnings.push_back("unusable cache entry, converting again: " + key + " in " + run.cache->describe() +
                           ": " + stored.error());
    }
    const std::size_t errors_before = errors.size();
    convert_candidate(run, p, errors);
    if (errors.size() != errors_before) return;  // a failed write is not a result to keep
    cache::Entry entry;
    std::string problem;
    auto stored = entry_to_store(run, p.out, entry, problem) ? run.cache->put(key, entry)
                                                             : cache::Result<bool>(cache::Error{problem});
    for (std::string& w : run.cache->take_warnings()) warnings.push_back(std::move(w));
    if (!stored)
        warnings.push_back("not cached: " + stored.error().message);
    else if (*stored)
        ++counts.stored;
}

}  // namespace stages

}  // namespace lsnif::converter
