// The scene manifest (OUTDIR/manifest.json, schema/manifest.schema.json): the one place that
// knows its format tag, its path rule and its text form, for the writers (`lsnif convert`,
// `lsnif merge`) and every reader (`lsnif eval`, `lsnif bench memory|rays`).
//
// Path rule: `inputs[].path` is relative to the directory that holds the manifest (absolute
// only where no relative path exists), so OUTDIR can be moved or archived together with its
// sources in the same relative layout and still be read from any working directory.
// `inputs[].given` keeps the path as it was given on the command line, for people only.
//
// Contract: no function here throws, exits or prints; failures come back as
// "<file>: <problem>" in `error`.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include <lsnif/converter/outcome.hpp>

#include <nlohmann/json.hpp>

namespace lsnif::converter {

inline constexpr const char* kManifestFormat = "lsnif-manifest/4";

// The form `inputs[].path` records for `input` (as given, relative to the current working
// directory or absolute) in a manifest written into `manifest_dir`: relative to
// `manifest_dir`, in generic ('/') form, or the absolute path if none exists.
std::string manifest_relative_path(const std::filesystem::path& input,
                                   const std::filesystem::path& manifest_dir);

// Writes OUTDIR/manifest.json atomically (creating OUTDIR), in the one text form every
// writer uses (`lsnif convert`, `lsnif merge`: their manifests must compare byte for byte).
// Returns "PATH: problem", or "" on success.
std::string write_manifest(const std::filesystem::path& outdir, const nlohmann::json& manifest);

// A manifest read back, with each input's file resolved for this process.
struct LoadedManifest {
    std::filesystem::path path;        // OUTDIR/manifest.json
    nlohmann::json doc;                // the parsed manifest: an object with inputs, meshes, instances
    std::vector<InputRecord> inputs;   // doc's inputs and meshes, read strictly (outcome_from_json)
    std::vector<MeshOutcome> meshes;   // each mesh's `input` names one of `inputs`
    std::vector<std::string> sources;  // per input: the file to import, usable from the current directory
};

// Reads OUTDIR/manifest.json and checks its format tag, its top-level shape and every input
// and mesh entry (an error names the first faulty field, "meshes[2].lsnif.file: missing"). `sources`
// overrides where the inputs are (one per manifest input, relative to the current directory,
// e.g. from `--source`); empty means the manifest's own paths, resolved from its directory.
// A manifest of an older format is refused with a message that says to re-run convert.
bool load_manifest(const std::filesystem::path& outdir, const std::vector<std::string>& sources,
                   LoadedManifest& out, std::string& error);

}  // namespace lsnif::converter
