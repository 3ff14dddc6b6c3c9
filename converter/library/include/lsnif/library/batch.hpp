// `lsnif batch`: an asset library through `lsnif convert` with a shared cache, as CI runs it
// (docs/pipeline.md "Batch"): inputs expanded from files, directories and list files, one
// line per asset, a JSON summary, JUnit XML, and exit codes a CI system can act on.
//
// Library code: never prints or exits; the CLI decides.
#pragma once

#include <lsnif/base/result.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/outcome.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::library {

// Exit codes of `lsnif batch` (and what the library reports as its verdict).
enum class BatchExit : int {
    ok = 0,      // every asset converted or rightly kept as BVH
    failed = 1,  // at least one input or asset failed; the others were converted
    usage = 2,   // bad command line (the CLI's) or options no conversion can meet
};

struct BatchOptions {
    // Scene files (by extension: scene::is_scene_file), directories (searched recursively
    // for scene files, in path order), or list files (any other file: one path per line,
    // relative to the list file's directory; blank lines and lines starting with '#' skipped).
    std::vector<std::string> inputs;
    // outdir and cache required; every `lsnif convert` setting. Assets record the command
    // "lsnif batch SETTINGS" (settings_arguments: canonical, inputs and outputs left out, the
    // asset's source is in its metadata), so that a single run, shards, --jobs and the steps
    // of a Ninja file write the same bytes; command_line is not used.
    converter::ConvertOptions convert;
    std::string junit_path;  // write JUnit XML here ("" = none)
    // --ninja FILE: plan only, and write a Ninja build file that converts the library with
    // one edge per unique candidate (docs/pipeline.md "Ninja"); `program` is the lsnif
    // executable its commands run (an absolute path).
    std::string ninja_path, program;
    // --plan FILE: plan only, and write the library's plan (LibraryPlan) for --from-plan.
    std::string plan_path;
    // --from-plan FILE: convert from a plan without planning the library again, after
    // checking that the tool and every input it needs are the ones planned. With `task`, that
    // one object (`lsnif batch --from-plan FILE --task K`, one task of a scheduler); with
    // convert.shard_count, that shard's share of the tasks; with neither, the whole library
    // through the cache, writing its manifest (the assembly step). The plan fixes every
    // recorded setting: convert holds only the run's own (cache, threads, output).
    std::string from_plan;
    std::optional<std::uint32_t> task;
};

// A library's plan (docs/pipeline.md "Plan once"), written by --plan, read by --from-plan.
struct PlannedInput {
    std::string path;    // absolute: a source path is part of every key
    std::string sha256;  // of the file's bytes when planned
};
struct PlannedTask {
    std::string key;        // the candidate's cache key
    std::size_t input = 0;  // into LibraryPlan::inputs
    std::string mesh;
    std::uint64_t estimated_ms = 0;  // estimated conversion time (docs/pipeline.md "Shards")
};
struct LibraryPlan {
    std::string version, identity;      // the lsnif that planned: tool_identity()
    std::vector<std::string> settings;  // settings_arguments of the planned conversion
    std::vector<PlannedInput> inputs;   // every scene file of the library, in order
    std::vector<PlannedTask> tasks;     // every unique candidate, costliest first: task K is tasks[K]
};
inline constexpr const char* kPlanFormat = "lsnif-plan/1";
nlohmann::json plan_json(const LibraryPlan& plan);
// Strict: an error names the field ("tasks[3].key: missing").
base::Result<LibraryPlan, std::string> plan_from_json(const nlohmann::json& j);

// What a run that converted a library did with its objects.
struct AssetCounts {
    std::size_t lsnif = 0;   // shipped as an LSNIF asset (converted or from the cache)
    std::size_t bvh = 0;     // stays in the BVH, with its reason
    std::size_t failed = 0;  // meshes and inputs that failed, and errors of the run itself
};
// The file a run that only plans wrote (--ninja FILE, --plan FILE), or the plan it ran from.
enum class PlanFile : std::uint8_t { ninja, plan, from_plan };
struct BatchResult {
    std::vector<std::string> scenes;        // what the inputs expanded to, in order, duplicates removed
    std::vector<std::string> input_errors;  // inputs that expanded to nothing usable
    converter::ConvertResult convert;
    std::vector<std::string> lines;  // one per asset (and per failed input), for people and logs
    // Set when the run converted a library (or took it from the cache); none when it planned.
    std::optional<AssetCounts> assets;
    std::optional<std::pair<PlanFile, std::string>> plan_file;  // set when the run planned: the file
    // Every error of the run: the inputs', the conversion's and the JUnit file's, in that order.
    std::vector<std::string> errors;
    BatchExit exit = BatchExit::ok;
};

// The `lsnif batch --json` document of a run: its scenes, asset lines and errors, the counts,
// the cache and scene memory when it converted, or the file it planned.
nlohmann::json batch_summary_json(const BatchResult& result);

// Expands inputs as BatchOptions::inputs says. Inputs that do not exist, unreadable list
// files and directories without scene files are reported in `errors` ("PATH: problem").
std::vector<std::string> expand_inputs(const std::vector<std::string>& inputs,
                                       std::vector<std::string>& errors);

// `on_line` receives each asset's line as soon as the asset is decided or converted (the
// same lines end up in BatchResult::lines, with the failed inputs'); `progress` every event.
BatchResult batch(const BatchOptions& options, const converter::ConvertProgress& progress = {},
                  const std::function<void(const std::string&)>& on_line = {});

// JUnit XML of a batch: one <testcase> per mesh (classname = the input file, name = the mesh;
// passed when converted or kept as BVH with its reason in <system-out>; <failure> when its
// asset could not be written), and one failed <testcase> per input that could not be read.
std::string junit_xml(const BatchResult& result);

// JUnit XML of a merged library (the same test cases as junit_xml; times are 0, since batch
// manifests carry no timings): what `lsnif merge --junit` writes.
struct MergeResult;
std::string merge_junit_xml(const MergeResult& merged);

// "I/N" (1 <= I <= N <= 10000) into a shard index and count; false with a one-line error.
bool parse_shard(const std::string& text, std::uint32_t& index, std::uint32_t& count, std::string& error);

struct MergeResult {
    std::vector<converter::InputRecord>
        inputs;  // the library's inputs and meshes, as OUTDIR/manifest.json lists them
    std::vector<converter::MeshOutcome> meshes;
    converter::SceneMemory memory;    // the merged scene's, as OUTDIR/manifest.json says it
    std::vector<std::string> errors;  // "PATH: problem"; nothing is written when not empty
};

// `lsnif merge`: the manifests of the N output directories of `lsnif batch --shard I/N`
// (I = 1..N, each once, same inputs, settings and plan) into one manifest in `outdir`, equal
// to a single run's: each candidate's entry from the shard that converted it, its asset
// copied, input paths made relative to `outdir`, the scene's memory summed again.
MergeResult merge(const std::vector<std::string>& shard_dirs, const std::string& outdir);

// The `lsnif merge --json` document of a merge: the shards, the output directory and the
// errors; when it succeeded, the merged manifest, its mesh count and the scene's memory.
nlohmann::json merge_summary_json(const std::vector<std::string>& shard_dirs, const std::string& outdir,
                                  const MergeResult& merged);

}  // namespace lsnif::library
