// `lsnif batch` (batch.hpp): inputs expanded, one convert() run with the cache, and the
// reports a CI system reads.
#include <lsnif/cache/remote.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/library/batch.hpp>
#include <lsnif/scene/scene.hpp>
#include "batch_internal.hpp"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>

namespace lsnif::library {

namespace fs = std::filesystem;
using converter::BvhYardstick;
using converter::ConvertOptions;
using converter::ConvertProgress;
using converter::GatePass;
using converter::GateVerdict;
using converter::InputRecord;
using converter::MeshClass;
using converter::MeshOutcome;
using converter::OutcomeFields;
using converter::ProgressEvent;
using nlohmann::json;
using namespace detail;

namespace detail {

std::string shell_word(const std::string& w) {
    const bool plain = !w.empty() && std::all_of(w.begin(), w.end(), [](char c) {
        return std::isalnum(static_cast<unsigned char>(c)) || std::strchr("/._-+=,:@%", c);
    });
    if (plain) return w;
    std::string out = "'";
    for (char c : w) {
        if (c == '\'') out += "'\\'";  // close, an escaped quote, reopen
        out += c;
    }
    out += '\'';
    return out;
}

std::string shell_line(const std::vector<std::string>& words) {
    std::string line;
    for (const std::string& w : words) {
        if (!line.empty()) line += ' ';
        line += shell_word(w);
    }
    return line;
}

std::string absolute(const std::string& p) {
    std::error_code ec;
    const fs::path a = fs::absolute(p, ec);
    return (ec ? fs::path(p) : a).lexically_normal().string();
}

}  // namespace detail

namespace {

// Scene files under `dir`, recursively, in path order.
std::vector<std::string> scenes_in(const fs::path& dir) {
    std::vector<std::string> found;
    std::error_code ec;
    for (auto it = fs::recursive_directory_iterator(dir, fs::directory_options::skip_permission_denied, ec);
         !ec && it != fs::recursive_directory_iterator(); it.increment(ec))
        if (it->is_regular_file(ec) && scene::is_scene_file(it->path())) found.push_back(it->path().string());
    std::sort(found.begin(), found.end());
    return found;
}

// A scene file or a directory (not a list: lists do not nest) into `out`.
void expand_path(const fs::path& p, const std::string& where, std::vector<std::string>& out,
                 std::vector<std::string>& errors) {
    std::error_code ec;
    if (fs::is_directory(p, ec)) {
        const std::vector<std::string> found = scenes_in(p);
        if (found.empty())
            errors.push_back(where + ": no scene files (.gltf .glb .obj .ply .off .stl) in this directory");
        out.insert(out.end(), found.begin(), found.end());
    } else if (!fs::exists(p, ec)) {
        errors.push_back(where + ": no such file or directory");
    } else {
        out.push_back(p.string());  // import reports a file it cannot read, as a failed input
    }
}

void expand_list(const fs::path& list, std::vector<std::string>& out, std::vector<std::string>& errors) {
    std::ifstream f(list);
    if (!f) {
        errors.push_back(list.string() + ": cannot read the list file");
        return;
    }
    std::string line;
    std::size_t number = 0, named = 0;
    while (std::getline(f, line)) {
        ++number;
        while (!line.empty() && (line.back() == '\r' || line.back() == ' ' || line.back() == '\t'))
            line.pop_back();
        const std::size_t start = line.find_first_not_of(" \t");
        if (start == std::string::npos || line[start] == '#') continue;
        ++named;
        fs::path p = line.substr(start);
        if (p.is_relative()) p = list.parent_path() / p;
        expand_path(p, list.string() + ":" + std::to_string(number) + ": " + p.string(), out, errors);
    }
    if (named == 0) errors.push_back(list.string() + ": the list file names no input");
}

std::string xml_escaped(const std::string& s) {
    std::string out;
    for (char c : s) {
        switch (c) {
            case '&': out += "&amp;"; break;
            case '<': out += "&lt;"; break;
            case '>': out += "&gt;"; break;
            case '"': out += "&quot;"; break;
            case '\'': out += "&apos;"; break;
            default:
                // XML 1.0 allows no control characters but tab, newline and carriage return.
                if (static_cast<unsigned char>(c) < 0x20 && c != '\t' && c != '\n' && c != '\r')
                    out += ' ';
                else
                    out += c;
        }
    }
    return out;
}

// The mesh's last reason, or its decision's name where it has none.
std::string last_reason(const MeshOutcome& m) {
    return m.reasons.empty() ? std::string(converter::decision_name(m.decision)) : m.reasons.back();
}

// A shipped asset's line: its memory against both BVHs, its held-out accuracy and image
// error, and what it ships without (the target's misses, the ray rules an image-shipped
// asset fails, an image gate raised above the calibrated one).
std::string shipped_line(const MeshOutcome& m, const std::string& who) {
    char buf[512];
    std::snprintf(buf, sizeof buf,
                  "lsnif    %s: %s, %" PRIu64 " bytes held in memory (%" PRIu64
                  " in the file; BVH: Embree %" PRIu64 ", compressed %" PRIu64
                  "), held-out visibility %.2f %%",
                  who.c_str(), m.asset->file.c_str(), m.asset->resident_bytes, m.asset->bytes,
                  m.stats ? m.stats->bvh.embree : 0, m.stats ? m.stats->bvh.compressed : 0,
                  100 * m.held_out->metrics.pooled.visibility_accuracy);
    std::string line = buf;
    if (m.held_out_images) {
        std::snprintf(buf, sizeof buf, ", image error %.4f", m.held_out_images->combined_object);
        line += buf;
    }
    const GateVerdict& gate = m.held_out->gate;
    if (gate.by == GatePass::images)
        line +=
            gate.above_calibrated ? ", shipped by images above the calibrated gate" : ", shipped by images";
    if (m.target && !m.target->misses.empty()) {
        line += "; target missed:";
        for (const std::string& miss : m.target->misses) line += " " + miss + ";";
        line.pop_back();
    }
    if (m.asset->reused.value_or(false)) line += " (reused)";
    return line;
}

std::string asset_line(const MeshOutcome& m, const std::string& input) {
    char buf[512];
    const std::string who = input + ": " + m.name;
    if (m.cls() == MeshClass::failed)
        std::snprintf(buf, sizeof buf, "failed   %s: %s", who.c_str(), last_reason(m).c_str());
    else if (m.asset)
        return shipped_line(m, who);
    else
        std::snprintf(buf, sizeof buf, "bvh      %s: %s", who.c_str(), last_reason(m).c_str());
    return buf;
}

// A path in a Ninja `build` line: '$', ' ', ':' and newlines escaped (ninja_syntax's rules).
std::string ninja_path(const std::string& p) {
    std::string out;
    for (char c : p) {
        if (c == '$' || c == ' ' || c == ':') out += '$';
        out += c == '\n' ? ' ' : c;
    }
    return out;
}

// A value of a Ninja variable (a command, a description): '$' escaped, one line.
std::string ninja_value(const std::string& v) {
    std::string out;
    for (char c : v) {
        if (c == '$') out += '$';
        out += c == '\n' ? ' ' : c;
    }
    return out;
}

// Whether `p` lies inside directory `dir` (both absolute and normal).
bool inside(const fs::path& p, const fs::path& dir) {
    const auto rel = p.lexically_relative(dir);
    return !rel.empty() && *rel.begin() != "..";
}

// What the Ninja file's regenerate edge watches: the scene files, list files and every
// directory searched (a file added or removed changes its directory's time).
std::vector<std::string> plan_dependencies(const BatchOptions& options,
                                           const std::vector<std::string>& scenes) {
    std::set<std::string> deps;
    for (const std::string& s : scenes) deps.insert(absolute(s));
    for (const std::string& in : options.inputs) {
        std::error_code ec;
        if (!fs::exists(in, ec)) continue;
        deps.insert(absolute(in));
        if (!fs::is_directory(in, ec)) continue;
        for (auto it =
                 fs::recursive_directory_iterator(in, fs::directory_options::skip_permission_denied, ec);
             !ec && it != fs::recursive_directory_iterator(); it.increment(ec))
            if (it->is_directory(ec)) deps.insert(absolute(it->path().string()));
    }
    return {deps.begin(), deps.end()};
}

// The plan's depfile (Makefile syntax, as Ninja reads it): `file` depends on `deps`.
std::string depfile_text(const std::string& file, const std::vector<std::string>& deps) {
    auto escaped = [](const std::string& p) {
        std::string out;
        for (char c : p) {
            if (c == ' ' || c == '#') out += '\\';
            if (c == '$') out += '$';
            out += c;
        }
        return out;
    };
    std::string t = escaped(file) + ":";
    for (const std::string& d : deps) t += " \\\n  " + escaped(d);
    return t + "\n";
}

// The text of the Ninja file (docs/pipeline.md "Ninja"): a regenerate edge (generator), one
// edge per object in a pool of depth 1 whose output is the object's cache entry, and the
// library edge that writes the manifest from the cache.
std::string ninja_text(const BatchOptions& options, const std::vector<PlannedObject>& objects,
                       const std::vector<std::string>& scenes, const cache::Store& store) {
    const ConvertOptions& c = options.convert;
    const std::string file = absolute(options.ninja_path), outdir = absolute(c.outdir),
                      cache_dir = absolute(c.cache), program = absolute(options.program);
    std::vector<std::string> inputs;
    for (const std::string& in : options.inputs) inputs.push_back(absolute(in));
    // Each step's threads (how fast, not what): as given, else all cores.
    std::vector<std::string> step_settings = converter::settings_arguments(c);
    if (c.threads) step_settings.insert(step_settings.end(), {"--threads", std::to_string(c.threads)});
    const std::string settings = shell_line(step_settings);
    const std::string junit =
        options.junit_path.empty() ? "" : " --junit " + shell_word(absolute(options.junit_path));
    std::string t;
    t += "# Written by `lsnif batch --ninja` (docs/pipeline.md \"Ninja\"): one edge per unique object.\n";
    t += "# Run `ninja -f " + file + "` (-k 0 to go on past a failure). Ninja plans again by itself\n";
    t += "# when an input, list file or searched directory changes.\n";
    t += "ninja_required_version = 1.7\n";
    t += "# Ninja's log beside this file, wherever ninja is run from.\n";
    t += "builddir = " + ninja_value(fs::path(file).parent_path().string()) + "\n\n";
    t += "lsnif = " + ninja_value(shell_word(program)) + "\n";
    t += "cache = " + ninja_value(shell_word(cache_dir)) + "\n";
    t += "outdir = " + ninja_value(shell_word(outdir)) + "\n";
    t += "settings = " + ninja_value(settings) + "\n\n";
    t += "# One conversion already uses every core: objects are converted one at a time.\n";
    t += "pool convert\n  depth = 1\n\n";
    t += "rule plan\n  command = $lsnif batch " + ninja_value(shell_line(inputs)) +
         " -o $outdir --cache $cache $settings" + ninja_value(junit) + " --ninja $out\n";
    t += "  description = lsnif: plan the library again\n  generator = 1\n";
    t += "  # What it read, as a depfile: a deleted input makes it plan again instead of an error.\n";
    t += "  depfile = $out.d\n\n";
    t += "# restat: a cache hit leaves the entry as it was, and the edge is clean afterwards.\n";
    t += "rule object\n  command = $lsnif batch $in --object $key -o $outdir --cache $cache $settings\n";
    t += "  description = lsnif: $mesh ($in)\n  pool = convert\n  restat = 1\n\n";
    t += "rule library\n  command = $lsnif batch " + ninja_value(shell_line(inputs)) +
         " -o $outdir --cache $cache $settings" + ninja_value(junit) + "\n";
    t += "  description = lsnif: " + ninja_value(outdir) + "/manifest.json\n\n";
    t += "build " + ninja_path(file) + ": plan | " + ninja_path(program) + "\n\n";
    std::string entries;
    for (const PlannedObject& o : objects) {
        const std::string entry = ninja_path(store.entry_path(o.key).string());
        entries += " " + entry;
        t += "build " + entry + ": object " + ninja_path(absolute(o.source)) + " | " + ninja_path(program) +
             "\n";
        t += "  key = " + o.key + "\n  mesh = " + ninja_value(o.mesh) + "\n";
    }
    t += "\nbuild " + ninja_path(outdir + "/manifest.json") + ": library" + entries + " |";
    for (const std::string& s : scenes) t += " " + ninja_path(absolute(s));
    t += " " + ninja_path(program) + "\n\ndefault " + ninja_path(outdir + "/manifest.json") + "\n";
    return t;
}

// Why --ninja cannot write a file for these options; empty when it can.
std::string ninja_problem(const BatchOptions& options) {
    const ConvertOptions& c = options.convert;
    if (c.shard_count > 0 || c.memory_budget > 0 || !c.only_keys.empty())
        return "--ninja cannot be combined with --shard, --memory-budget or --object: Ninja schedules "
               "every object itself";
    if (options.program.empty()) return "--ninja needs the path of the lsnif executable";
    if (cache::is_url(c.cache) || !c.cache_local.empty())
        return "--ninja needs --cache to be a directory: its edges' outputs are the cache's entry files";
    for (const std::string& in : options.inputs) {
        std::error_code ec;
        if (!fs::is_directory(in, ec)) continue;
        const fs::path dir = absolute(in);
        for (const std::string& out : {options.ninja_path, c.outdir, c.cache})
            if (inside(absolute(out), dir))
                return out + ": inside the input directory " + in +
                       " (writing there would make Ninja plan again on every run)";
    }
    return {};
}

}  // namespace

std::vector<std::string> expand_inputs(const std::vector<std::string>& inputs,
                                       std::vector<std::string>& errors) {
    std::vector<std::string> all;
    for (const std::string& in : inputs) {
        const fs::path p(in);
        std::error_code ec;
        if (fs::is_regular_file(p, ec) && !scene::is_scene_file(p))
            expand_list(p, all, errors);
        else
            expand_path(p, in, all, errors);
    }
    std::vector<std::string> unique;
    std::set<std::string> seen;
    for (const std::string& s : all) {
        std::error_code ec;
        const std::string id = fs::weakly_canonical(s, ec).string();
        if (seen.insert(ec ? s : id).second) unique.push_back(s);
    }
    return unique;
}

namespace {

// --ninja: plans the library (a dry run) and writes the Ninja file atomically.
void plan_ninja(const BatchOptions& options, const ConvertProgress& progress, BatchResult& r) {
    if (std::string why = ninja_problem(options); !why.empty()) {
        r.convert.errors.push_back(why);
        r.exit = BatchExit::usage;
        return;
    }
    auto store = cache::Store::open(absolute(options.convert.cache));  // entry paths go in the file
    if (!store) {
        r.convert.errors.push_back(store.error().message);
        r.exit = BatchExit::failed;
        return;
    }
    const auto objects = plan_library(options.convert, progress, r);
    if (!objects) return;
    const std::string file = absolute(options.ninja_path);
    std::error_code ec;
    fs::create_directories(fs::path(file).parent_path(), ec);
    // The depfile first: a Ninja file is never there without what it depends on.
    for (const auto& [path, text] :
         {std::pair{file + ".d", depfile_text(file, plan_dependencies(options, r.scenes))},
          std::pair{file, ninja_text(options, *objects, r.scenes, *store)}})
        if (const format::Error e = format::write_text_atomically(path, text)) {
            r.convert.errors.push_back(e.message);
            r.exit = BatchExit::failed;
            return;
        }
    r.lines.push_back("planned  " + std::to_string(objects->size()) +
                      " objects to convert: " + options.ninja_path);
    // Inputs that cannot be read fail in the library step, where CI sees them; failing here
    // would stop Ninja each time it plans again.
    for (const std::string& e : r.input_errors)
        r.convert.warnings.push_back(e + " (the library step will fail on it)");
    for (const std::string& e : r.convert.errors)
        r.convert.warnings.push_back(e + " (the library step will fail on it)");
    r.input_errors.clear();
    r.convert.errors.clear();
    r.exit = BatchExit::ok;
}

// The run's errors as BatchResult::errors lists them: the inputs', then the conversion's.
void collect_errors(BatchResult& r) {
    r.errors = r.input_errors;
    r.errors.insert(r.errors.end(), r.convert.errors.begin(), r.convert.errors.end());
}

// A run that planned (--ninja, --plan FILE, or --from-plan without a task): what was
// planned, no counts.
void planned(PlanFile kind, const std::string& file, BatchResult& r) {
    r.plan_file = {kind, file};
    collect_errors(r);
}

}  // namespace

namespace detail {

std::optional<std::vector<PlannedObject>> plan_library(ConvertOptions c, const ConvertProgress& progress,
                                                       BatchResult& r) {
    for (std::string& scene : r.scenes) scene = absolute(scene);
    c.inputs = r.scenes;
    c.dry_run = true;
    r.convert = converter::convert(c, progress);
    if (r.convert.usage_error) {
        r.exit = BatchExit::usage;
        return std::nullopt;
    }
    std::map<std::string, PlannedObject> unique;
    for (const MeshOutcome& m : r.convert.meshes)
        if (m.cache_key)
            unique.emplace(*m.cache_key, PlannedObject{*m.cache_key, r.scenes.at(m.input), m.name,
                                                       std::size_t(m.input), *m.estimated_ms});
    std::vector<PlannedObject> objects;
    for (auto& [key, o] : unique) objects.push_back(std::move(o));
    std::stable_sort(objects.begin(), objects.end(), [](const PlannedObject& a, const PlannedObject& b) {
        return a.estimated_ms > b.estimated_ms;  // costliest first, then by key
    });
    return objects;
}

void convert_library(const BatchOptions& options, ConvertOptions c, const ConvertProgress& progress,
                     const std::function<void(const std::string&)>& on_line, BatchResult& r) {
    std::size_t converted = 0, bvh = 0, failed = r.input_errors.size();
    if (!r.scenes.empty()) {
        c.inputs = r.scenes;
        c.command_line = "lsnif batch " + shell_line(converter::settings_arguments(c));
        c.write_gltf = false;  // a library, not a scene
        // One object's job (--object, --from-plan --task) reports its objects: the meshes that
        // classification decided belong to the library's own run.
        const bool objects_only = !c.only_keys.empty();
        const auto reported = [objects_only](const MeshOutcome& m) {
            return m.cls() != MeshClass::deferred &&
                   !(objects_only && converter::decided_in_triage(m.decision));
        };
        const auto forward = [&](const ProgressEvent& e) {
            if (e.stage == "done" && e.outcome && on_line && reported(*e.outcome))
                on_line(asset_line(*e.outcome, r.scenes.at(e.outcome->input)));
            if (progress) progress(e);
        };
        r.convert = converter::convert(c, forward);
        if (r.convert.usage_error) {
            r.exit = BatchExit::usage;
            return;
        }
        for (const InputRecord& in : r.convert.inputs)
            if (!in.ok()) {
                r.lines.push_back("failed   " + *in.error);
                ++failed;
            }
        for (const MeshOutcome& m : r.convert.meshes) {
            if (!reported(m)) continue;
            r.lines.push_back(asset_line(m, r.convert.inputs.at(m.input).given));
            m.cls() == MeshClass::failed ? ++failed : m.asset ? ++converted : ++bvh;
        }
        // Errors that concern the run and no input or mesh (the manifest could not be written).
        const std::size_t attributed = failed - r.input_errors.size();
        if (r.convert.errors.size() > attributed) failed += r.convert.errors.size() - attributed;
    } else if (r.input_errors.empty()) {
        r.input_errors.push_back("no inputs");
        ++failed;
    }
    r.assets = AssetCounts{converted, bvh, failed};
    collect_errors(r);
    r.exit = failed ? BatchExit::failed : BatchExit::ok;
    if (!options.junit_path.empty()) {
        const format::Error e = format::write_text_atomically(options.junit_path, junit_xml(r));
        if (e) {
            r.errors.push_back(e.message);
            r.input_errors.push_back(e.message);
            r.exit = BatchExit::failed;
        }
    }
}

}  // namespace detail

BatchResult batch(const BatchOptions& options, const ConvertProgress& progress,
                  const std::function<void(const std::string&)>& on_line) {
    BatchResult r;
    if (!options.from_plan.empty()) {  // the plan names the inputs
        run_from_plan(options, progress, on_line, r);
        if (!r.assets) planned(PlanFile::from_plan, options.from_plan, r);
        return r;
    }
    r.scenes = expand_inputs(options.inputs, r.input_errors);
    for (const std::string& e : r.input_errors) r.lines.push_back("failed   " + e);
    if (!options.ninja_path.empty()) {
        plan_ninja(options, progress, r);
        planned(PlanFile::ninja, options.ninja_path, r);
    } else if (!options.plan_path.empty()) {
        write_plan(options, progress, r);
        planned(PlanFile::plan, options.plan_path, r);
    } else {
        convert_library(options, options.convert, progress, on_line, r);
    }
    return r;
}

nlohmann::json batch_summary_json(const BatchResult& r) {
    nlohmann::json j = {{"scenes", r.scenes},
                        {"lines", r.lines},
                        {"errors", r.errors},
                        {"warnings", r.convert.warnings},
                        {"exit_code", int(r.exit)}};
    if (r.plan_file) {
        static constexpr const char* kKeys[] = {"ninja", "plan", "from_plan"};
        j[kKeys[int(r.plan_file->first)]] = r.plan_file->second;
    }
    if (r.assets)
        j["assets"] = {{"lsnif", r.assets->lsnif}, {"bvh", r.assets->bvh}, {"failed", r.assets->failed}};
    if (r.assets && r.convert.cache) {
        const converter::CacheCounts& c = *r.convert.cache;
        j["cache"] = {
            {"location", c.location}, {"hits", c.hits}, {"stored", c.stored}, {"corrupt", c.corrupt}};
    }
    if (r.assets && r.convert.memory) j["scene_memory"] = converter::scene_memory_json(*r.convert.memory);
    if (r.assets && !r.convert.manifest_path.empty()) j["manifest"] = r.convert.manifest_path;
    return j;
}

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

std::string junit_xml(const BatchResult& r) {
    std::string cases;
    std::size_t tests = 0, failures = 0;
    double total = 0;
    auto add_case = [&](const std::string& classname, const std::string& name, double seconds,
                        const std::string& failure, const std::string& out) {
        ++tests;
        total += seconds;
        char t[32];
        std::snprintf(t, sizeof t, "%.3f", seconds);
        cases += "    <testcase classname=\"" + xml_escaped(classname) + "\" name=\"" + xml_escaped(name) +
                 "\" time=\"" + t + "\">\n";
        if (!failure.empty()) {
            ++failures;
            cases += "      <failure message=\"" + xml_escaped(failure) + "\" type=\"lsnif\">" +
                     xml_escaped(failure) + "</failure>\n";
        }
        if (!out.empty()) cases += "      <system-out>" + xml_escaped(out) + "</system-out>\n";
        cases += "    </testcase>\n";
    };
    for (const std::string& e : r.input_errors) add_case("inputs", e.substr(0, e.find(':')), 0, e, "");
    for (const InputRecord& in : r.convert.inputs)
        if (!in.ok()) add_case(in.given, "import", 0, *in.error, "");
    for (const MeshOutcome& m : r.convert.meshes) {
        const std::string& input = r.convert.inputs.at(m.input).given;
        const std::string line = asset_line(m, input);
        const bool failed = m.cls() == MeshClass::failed;
        add_case(input, m.name, m.timings.total(), failed ? line : "", failed ? "" : line);
    }
    char head[256];
    std::snprintf(head, sizeof head,
                  "tests=\"%zu\" failures=\"%zu\" errors=\"0\" skipped=\"0\" time=\"%.3f\"", tests, failures,
                  total);
    return std::string("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n") + "<testsuites name=\"lsnif batch\" " +
           head + ">\n  <testsuite name=\"lsnif batch\" " + head + ">\n" + cases +
           "  </testsuite>\n</testsuites>\n";
}

std::string merge_junit_xml(const MergeResult& merged) {
    BatchResult r;
    r.convert.inputs = merged.inputs;
    r.convert.meshes = merged.meshes;
    return junit_xml(r);
}

bool parse_shard(const std::string& text, std::uint32_t& index, std::uint32_t& count, std::string& error) {
    const std::size_t slash = text.find('/');
    std::uint32_t i = 0, n = 0;
    auto number = [](std::string_view t, std::uint32_t& v) {
        const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
        return !t.empty() && ec == std::errc() && end == t.data() + t.size();
    };
    if (slash == std::string::npos || !number(std::string_view(text).substr(0, slash), i) ||
        !number(std::string_view(text).substr(slash + 1), n) || n < 1 || n > 10000 || i < 1 || i > n) {
        error = "expected I/N with 1 <= I <= N <= 10000, e.g. 2/3";
        return false;
    }
    index = i;
    count = n;
    return true;
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
