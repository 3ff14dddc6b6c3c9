// `lsnif convert`: the run of every mesh through the stages (convert_stages.hpp) and the
// manifest; see convert.hpp for the contracts.
#include <lsnif/base/clock.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/cache/remote.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/gltf_out.hpp>
#include <lsnif/converter/manifest.hpp>
#include "convert_stages.hpp"

#include <deque>
#include <set>

namespace lsnif::converter {

using nlohmann::json;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using base::seconds_since;

namespace stages {

// Why a candidate stays BVH when the scene already fits the budget.
std::string fits_without_it(std::uint64_t total, std::uint64_t budget) {
    return "the scene fits the memory budget without it (" + std::to_string(total) + " of " +
           std::to_string(budget) + " bytes with this mesh as BVH)";
}

// What settling one candidate produced besides its outcome (p.out); kept apart per candidate
// so that concurrent jobs (--jobs) never share a vector, and merged in candidate order afterwards.
struct Settled {
    std::uint64_t after = 0;
    std::vector<std::string> errors, warnings;
    CacheCounts counts;
};

// Settles candidate `p` given the scene's memory `total` so far: recorded as another shard's,
// kept as BVH because the budget is met, or converted (through the cache). Reports "done".
Settled settle_candidate(const Run& run, Triaged& p, std::uint32_t owner, std::uint64_t total) {
    Settled s;
    s.after = p.bvh_bytes;
    const std::uint64_t budget = run.opt.memory_budget;
    const std::vector<std::string>& only = run.opt.only_keys;
    if (run.opt.shard_count > 0 && owner != run.opt.shard_index) {
        p.out.settle(Decision::other_shard, "converted by shard " + std::to_string(owner) + " of " +
                                                std::to_string(run.opt.shard_count));
    } else if (!only.empty() && std::find(only.begin(), only.end(), cache_key(run, p)) == only.end()) {
        p.out.settle(Decision::left_to_another_job, kLeftToAnotherJob);
    } else if (budget > 0 && total <= budget && !p.forced()) {
        p.out.settle(Decision::budget_met, fits_without_it(total, budget));
    } else {
        convert_cached(run, p, s.errors, s.warnings, s.counts);
        s.after = bytes_after(p);
    }
    if (run.opt.shard_count > 0) p.out.shard = owner;
    if (run.opt.dry_run) {
        p.out.cache_key = cache_key(run, p);
        p.out.estimated_ms = estimated_cost_ms(run, p);
    }
    run.report({p.mesh->name, "done", 0, 0, 0, 0, &p.out});
    p.candidate.reset();  // its Embree scene (the largest thing a candidate holds)
    p.occupancy.reset();
    return s;
}

// Settles the candidates in `order`: one after another when a budget decides each from the
// ones before it, otherwise up to run.opt.jobs at a time, each on its own thread (the
// conversions are independent; their results do not depend on which job ran them).
std::vector<Settled> settle_candidates(const Run& run, std::vector<Triaged>& triaged,
                                       const std::vector<std::size_t>& order,
                                       std::vector<std::uint64_t>& after) {
    std::vector<Settled> settled(triaged.size());
    const std::vector<std::uint32_t> owner = shard_owners(run, triaged);
    if (run.opt.memory_budget > 0 || run.opt.jobs <= 1 || order.size() <= 1) {
        for (std::size_t i : order) {
            const std::uint64_t total = std::accumulate(after.begin(), after.end(), std::uint64_t(0));
            settled[i] = settle_candidate(run, triaged[i], owner[i], total);
            after[i] = settled[i].after;
        }
        return settled;
    }
    std::atomic<std::size_t> next{0};
    const auto jobs = std::uint32_t(std::min<std::size_t>(run.opt.jobs, order.size()));
    std::vector<std::thread> workers;
    std::mutex failed_mutex;
    std::exception_ptr failed;  // the first exception a job threw, rethrown once all joined
    auto work = [&] {
        try {
            for (std::size_t k; (k = next.fetch_add(1)) < order.size();) {
                const std::size_t i = order[k];
                settled[i] = settle_candidate(run, triaged[i], owner[i], 0);
            }
        } catch (...) {
            std::lock_guard lock(failed_mutex);
            if (!failed) failed = std::current_exception();
            next = order.size();
        }
    };
    // Plain threads, not base::run_on_threads: each job's conversion uses the pool itself.
    for (std::uint32_t j = 1; j < jobs; ++j) workers.emplace_back(work);
    work();
    for (std::thread& w : workers) w.join();
    if (failed) std::rethrow_exception(failed);
    for (std::size_t i : order) after[i] = settled[i].after;
    return settled;
}

std::vector<MeshOutcome> convert_meshes(const Run& run, std::vector<Triaged>& triaged,
                                        std::vector<std::string>& errors, std::vector<std::string>& warnings,
                                        CacheCounts& counts) {
    std::vector<std::uint64_t> after(triaged.size());
    for (std::size_t i = 0; i < triaged.size(); ++i) {
        after[i] = triaged[i].bvh_bytes;
        if (triaged[i].decided) run.report({triaged[i].mesh->name, "done", 0, 0, 0, 0, &triaged[i].out});
    }
    mark_shared_assets(run, triaged);
    const std::vector<std::size_t> order = conversion_order(triaged, run.opt.memory_budget > 0);
    std::vector<Settled> settled = settle_candidates(run, triaged, order, after);
    for (std::size_t i = 0; i < triaged.size(); ++i) {
        if (!triaged[i].leader) continue;
        follow_leader(triaged[i], triaged[*triaged[i].leader]);
        after[i] = bytes_after(triaged[i]);
        run.report({triaged[i].mesh->name, "done", 0, 0, 0, 0, &triaged[i].out});
    }
    for (std::size_t i : order) {
        errors.insert(errors.end(), settled[i].errors.begin(), settled[i].errors.end());
        warnings.insert(warnings.end(), settled[i].warnings.begin(), settled[i].warnings.end());
        counts.hits += settled[i].counts.hits;
        counts.stored += settled[i].counts.stored;
        counts.corrupt += settled[i].counts.corrupt;
    }
    std::vector<MeshOutcome> outcomes;
    outcomes.reserve(triaged.size());
    for (std::size_t i = 0; i < triaged.size(); ++i) {
        MeshOutcome& o = outcomes.emplace_back(std::move(triaged[i].out));
        o.memory =
            MeshMemory{triaged[i].bvh_bytes, after[i], run.opt.dry_run && o.cls() == MeshClass::complex};
    }
    return outcomes;
}

void keep_scene_place(MeshOutcome& result, const MeshOutcome& own) {
    result.id = own.id;
    result.name = own.name;
    result.input = own.input;
    result.source_mesh = own.source_mesh;
    result.instances = own.instances;
    result.timings = own.timings;
}

void follow_leader(Triaged& follower, const Triaged& leader) {
    MeshOutcome o = leader.out;
    const MeshOutcome& own = follower.out;
    keep_scene_place(o, own);
    o.reasons.assign(own.reasons.begin(), own.reasons.begin() + std::ptrdiff_t(follower.triage_reasons));
    o.reasons.insert(o.reasons.end(), leader.out.reasons.begin() + std::ptrdiff_t(leader.triage_reasons),
                     leader.out.reasons.end());
    o.reasons.push_back("the same geometry and settings as mesh '" + leader.out.name + "' of input " +
                        std::to_string(leader.out.input) + ": its result" + (o.asset ? " and asset" : ""));
    if (o.asset) o.asset->reused = true;
    follower.out = std::move(o);
    follower.candidate.reset();
    follower.occupancy.reset();
}

// The cache keys of the candidates; call before convert_meshes, which releases them.
std::set<std::string> candidate_keys(const Run& run, std::vector<Triaged>& triaged) {
    std::set<std::string> keys;
    for (Triaged& p : triaged)
        if (!p.decided) keys.insert(cache_key(run, p));
    return keys;
}

// --object: every selected key names a candidate, and its result is in the cache.
void check_selected_stored(const Run& run, const cache::Cache& store, const std::set<std::string>& keys,
                           std::vector<std::string>& errors) {
    for (const std::string& key : run.opt.only_keys) {
        std::error_code ec;
        if (!keys.count(key))
            errors.push_back("--object " + key +
                             ": no candidate of the inputs has this cache key (the inputs, the settings "
                             "or the build changed since it was planned: plan again)");
        else if (!store.has(key))
            errors.push_back("--object " + key + ": the result is not in the cache " + store.describe());
    }
}

std::string unreachable_budget(const Run& run, const std::vector<Triaged>& triaged) {
    std::uint64_t fixed = 0;
    for (const Triaged& p : triaged)
        if (p.decided) fixed += p.bvh_bytes;
    if (run.opt.memory_budget == 0 || run.opt.memory_budget >= fixed) return {};
    return "--memory-budget " + std::to_string(run.opt.memory_budget) +
           " bytes is below the BVHs of the meshes that stay BVH in any case (" + std::to_string(fixed) +
           " bytes: fewer triangles than the classifier converts, --simple, or no memory benefit): no "
           "conversion can meet it";
}

MeshOutcome new_outcome(const scene::Scene& sc, std::size_t in, std::size_t k, std::size_t id) {
    const scene::Mesh& mesh = sc.meshes[k];
    MeshOutcome o;
    o.id = id;
    o.name = mesh.name;
    o.input = in;
    o.source_mesh = k;
    o.triangles = mesh.triangle_count();
    o.vertices = mesh.vertex_count();
    o.geometry_hash = scene::geometry_hash(mesh);
    for (const auto& i : sc.instances) o.instances += i.mesh == k;
    return o;
}

}  // namespace stages

using namespace stages;

namespace {

// Why the options split work that a memory budget must decide in order; empty when they do not.
std::string budget_conflict(const ConvertOptions& opt) {
    if (opt.memory_budget == 0) return {};
    const char* other = opt.shard_count > 0 ? "--shard" : opt.jobs > 1 ? "--jobs" : nullptr;
    if (!other) return {};
    return std::string(other) +
           " and --memory-budget cannot be combined: the budget decides each conversion from the ones "
           "before it";
}

}  // namespace

std::string arithmetic_id(Arithmetic a) {
    if (a == Arithmetic::machine &&
        trainer::resolve_precision(trainer::MlpPrecision::automatic) == trainer::MlpPrecision::bf16)
        return "machine-" + trainer::mlp_arithmetic(trainer::MlpPrecision::automatic);
    return "canonical-" + std::to_string(kCanonicalArithmeticVersion);
}

bool parse_arithmetic(const std::string& text, Arithmetic& out) {
    if (text == "canonical")
        out = Arithmetic::canonical;
    else if (text == "machine")
        out = Arithmetic::machine;
    else
        return false;
    return true;
}

std::uint32_t threads_per_job(const ConvertOptions& opt) {
    return std::max(1u, base::resolve_threads(opt.threads) / std::max(1u, opt.jobs));
}

namespace {

// The cache a run reads and writes, or null without --cache (or for a dry run); false (and
// an error) when the directory cannot be opened.
bool open_cache(const ConvertOptions& opt, std::shared_ptr<const cache::Cache>& store,
                std::vector<std::string>& errors) {
    if (opt.cache.empty() || opt.dry_run) return true;
    auto opened = cache::Cache::open(
        {opt.cache, opt.cache_local, opt.cache_read_only, opt.cache_timeout, opt.cache_token});
    if (!opened) {
        errors.push_back(opened.error().message);
        return false;
    }
    store = std::make_shared<const cache::Cache>(std::move(*opened));
    return true;
}

// `progress` as concurrent jobs may call it, from their own threads: one at a time.
ConvertProgress serialized(const ConvertProgress& progress, std::uint32_t jobs) {
    if (!progress || jobs <= 1) return progress;
    auto mutex = std::make_shared<std::mutex>();
    return [progress, mutex](const ProgressEvent& e) {
        std::lock_guard lock(*mutex);
        progress(e);
    };
}

// Every input imported and its meshes triaged (classified, voxelized; decided or candidates).
struct Imported {
    json instances = json::array();   // as the manifest records them
    std::deque<scene::Scene> scenes;  // every input stays imported: candidates borrow their meshes
    std::vector<GltfSource> sources;  // per input, for scene.gltf
    std::vector<Triaged> triaged;
    std::size_t ok_inputs = 0;
};

// Imports one input, plans its meshes and records its instances; an input that cannot be
// read is an error of the run, recorded in the manifest's inputs, and the run goes on.
void import_input(const Run& run, std::size_t in, Imported& im, ConvertResult& res) {
    const std::string& path = run.opt.inputs[in];
    run.report({path, "import"});
    const auto t0 = Clock::now();
    auto imported = scene::import_scene(path);
    res.import_seconds += seconds_since(t0);
    InputRecord& record = res.inputs.emplace_back();
    record.path = manifest_relative_path(path, run.outdir);
    record.given = path;
    im.sources.push_back({path, nullptr});
    if (!imported.ok()) {
        res.errors.push_back(imported.error);
        record.error = imported.error;
        return;
    }
    ++im.ok_inputs;
    const scene::Scene& sc = im.scenes.emplace_back(std::move(imported.scene));
    im.sources.back().scene = &sc;
    record.warnings = sc.warnings;
    for (const auto& w : sc.warnings) res.warnings.push_back(path + ": " + w);
    const std::size_t first_id = im.triaged.size();
    for (std::size_t k = 0; k < sc.meshes.size(); ++k)
        im.triaged.push_back(
            triage_mesh(run, path, sc.meshes[k], new_outcome(sc, in, k, im.triaged.size()), res.warnings));
    for (const auto& i : sc.instances)
        im.instances.push_back({{"mesh", first_id + i.mesh},
                                {"name", i.node_name},
                                {"transform", std::vector<float>(i.transform.begin(), i.transform.end())}});
}

// The manifest (and scene.gltf) of a finished run into OUTDIR; errors into `res`.
void write_outputs(const Run& run, const Imported& im, ConvertResult& res) {
    const OutcomeFields fields =
        run.opt.reproducible_manifest ? OutcomeFields::reproducible : OutcomeFields::all;
    res.manifest = manifest_json(run, res.inputs, res.meshes, im.instances, *res.memory, fields);
    if (run.opt.shard_count > 0)
        res.manifest["shard"] = {{"index", run.opt.shard_index}, {"count", run.opt.shard_count}};
    if (std::string e = write_manifest(run.outdir, res.manifest); !e.empty()) res.errors.push_back(e);
    res.manifest_path = (run.outdir / "manifest.json").string();
    if (run.opt.write_gltf) {
        if (std::string e = write_scene_gltf(run.outdir, im.sources, res.meshes); !e.empty())
            res.errors.push_back(e);
        else
            res.gltf_path = (run.outdir / "scene.gltf").string();
    }
}

}  // namespace

ConvertResult convert(const ConvertOptions& opt, const ConvertProgress& progress) {
    ConvertResult res;
    res.dry_run = opt.dry_run;
    Preset preset;
    std::string error;
    if (!resolve_preset(opt, preset, error)) {
        res.errors.push_back(error);
        return res;
    }
    std::shared_ptr<const cache::Cache> store;
    if (!open_cache(opt, store, res.errors)) {
        res.usage_error = !opt.cache.empty() && cache::is_url(opt.cache);  // a URL it cannot use
        return res;
    }
    if (std::string why = budget_conflict(opt); !why.empty()) {
        res.errors.push_back(why);
        res.usage_error = true;
        return res;  // nothing imported, trained or written
    }
    const Run run{opt,  std::move(preset), threads_per_job(opt), opt.outdir, serialized(progress, opt.jobs),
                  store};
    Imported im;
    for (std::size_t in = 0; in < opt.inputs.size(); ++in) import_input(run, in, im, res);
    res.instances = im.instances.size();
    if (std::string why = unreachable_budget(run, im.triaged); !why.empty()) {
        res.errors.push_back(why);
        res.usage_error = true;
        return res;  // nothing trained, nothing written
    }
    CacheCounts counts;
    const std::set<std::string> keys =
        opt.only_keys.empty() ? std::set<std::string>() : candidate_keys(run, im.triaged);
    res.meshes = convert_meshes(run, im.triaged, res.errors, res.warnings, counts);
    res.memory = scene_memory(res.meshes, run.preset.classify.yardstick, opt.memory_budget, opt.dry_run);
    if (store) {
        res.cache = counts;
        res.cache->location = store->describe();
    }
    if (!res.memory->fits())
        res.warnings.push_back("the scene needs " + std::to_string(res.memory->after) +
                               " bytes, over the memory budget of " + std::to_string(opt.memory_budget) +
                               " bytes, with every candidate that passed converted");
    if (im.ok_inputs > 0 && !opt.dry_run) {
        if (!opt.only_keys.empty()) {  // one job's share: its cache entries, no manifest
            if (store) check_selected_stored(run, *store, keys, res.errors);
        } else {
            write_outputs(run, im, res);
        }
    }
    return res;
}

json convert_report_json(const ConvertResult& res) {
    json inputs = json::array(), meshes = json::array();
    for (const InputRecord& in : res.inputs) inputs.push_back(input_json(in));
    for (const MeshOutcome& o : res.meshes) meshes.push_back(outcome_json(o));
    json report = {{"inputs", inputs},
                   {"meshes", meshes},
                   {"instances", res.instances},
                   {"errors", res.errors},
                   {"warnings", res.warnings}};
    if (res.memory) report["scene_memory"] = scene_memory_json(*res.memory);
    report["timings"] = {{"import", res.import_seconds}};  // per-mesh stages are in meshes[].timings
    if (res.dry_run) report["dry_run"] = true;
    if (res.cache)
        report["cache"] = {{"location", res.cache->location},
                           {"hits", res.cache->hits},
                           {"stored", res.cache->stored},
                           {"corrupt", res.cache->corrupt}};
    if (!res.manifest_path.empty()) report["manifest"] = res.manifest_path;
    if (!res.gltf_path.empty()) report["gltf"] = res.gltf_path;
    return report;
}

}  // namespace lsnif::converter
