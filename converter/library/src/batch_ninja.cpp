// `lsnif batch --ninja` (batch.hpp): the library planned once (a dry run) and written as a
// Ninja file with one edge per unique object, and the depfile that makes Ninja plan again.
#include <lsnif/cache/remote.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/library/batch.hpp>
#include "batch_internal.hpp"

#include <filesystem>
#include <set>
#include <string>
#include <utility>
#include <vector>

namespace lsnif::library::detail {

namespace fs = std::filesystem;
using converter::ConvertOptions;
using converter::ConvertProgress;

namespace {

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
    for (const std::string& s : scenes) t.append(" ").append(ninja_path(absolute(s)));
    t.append(" ").append(ninja_path(program));
    t += "\n\ndefault " + ninja_path(outdir + "/manifest.json") + "\n";
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

// --ninja: plans the library (a dry run) and writes the Ninja file atomically.
void plan_ninja(const BatchOptions& options, const ConvertProgress& progress, BatchResult& r) {
    if (std::string why = ninja_problem(options); !why.empty()) return fail(r, why, BatchExit::usage);
    auto store = cache::Store::open(absolute(options.convert.cache));  // entry paths go in the file
    if (!store) return fail(r, store.error().message);
    const auto objects = plan_library(options.convert, progress, r);
    if (!objects) return;
    const std::string file = absolute(options.ninja_path);
    std::error_code ec;
    fs::create_directories(fs::path(file).parent_path(), ec);
    // The depfile first: a Ninja file is never there without what it depends on.
    for (const auto& [path, text] :
         {std::pair{file + ".d", depfile_text(file, plan_dependencies(options, r.scenes))},
          std::pair{file, ninja_text(options, *objects, r.scenes, *store)}})
        if (const format::Error e = format::write_text_atomically(path, text)) return fail(r, e.message);
    r.lines.push_back("planned  " + std::to_string(objects->size()) +
                      " objects to convert: " + options.ninja_path);
    // Inputs that cannot be read fail in the library step, where CI sees them; failing here
    // would stop Ninja each time it plans again.
    defer_errors(r, "library step");
}

}  // namespace lsnif::library::detail
