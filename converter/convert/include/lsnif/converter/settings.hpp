// The settings of `lsnif convert` and `lsnif batch`, one row each. The table is the one place
// a setting is described: the command line registers every row (converter/cli/src/main.cpp), its
// help shows the default, `settings_arguments` writes the rows that change a result (what a
// batch records and a Ninja step passes on), cache keys hash them (`mesh_settings_key`) and
// the manifest's `settings` holds them (`settings_json`). A new setting is one new row.
#pragma once

#include <lsnif/converter/convert.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <string>
#include <vector>

namespace lsnif::converter {

// What a setting changes (docs/pipeline.md "Cache keys").
enum class SettingScope : std::uint8_t {
    mesh,    // a mesh's result: recorded (batch command, manifest) and part of every cache key
    report,  // what a mesh's record reports, never its asset: recorded and part of the cache key
             // of its record, not of the asset's name or bytes
    scene,   // which meshes convert, or are forced either way: recorded, not part of a mesh's key
             // (whether a mesh was forced is: cache_key)
    run,     // how fast, or what is printed: neither recorded nor keyed
};

struct Setting {
    const char* names;  // CLI11 form: "--seed", "-j,--jobs"
    const char* value;  // the value's name in --help ("N", "NAME"); nullptr for a flag
    bool repeated;      // given once per value (--complex A --complex B)
    SettingScope scope;
    const char* manifest;      // its key in the manifest's settings; nullptr: not recorded there
    const char* default_text;  // what --help shows as the default
    const char* help;
    // Reads one value (a flag: "") into `opt`; false with `error` (without the option's name)
    // for a value the setting does not take. `warning` (empty unless set) tells the user of a
    // deprecated form that was still understood.
    bool (*set)(ConvertOptions& opt, const std::string& value, std::string& error, std::string& warning);
    // The values the command line would give for `opt`, in a canonical form; empty when `opt`
    // has the default (nothing to write); {""} for a flag that is on.
    std::vector<std::string> (*get)(const ConvertOptions& opt);
    // Its manifest value for `opt`; null: not written (the default of an override).
    nlohmann::json (*to_json)(const ConvertOptions& opt);
};

// Every setting, in the order of --help and of settings_arguments.
const std::vector<Setting>& settings_table();

// "--jobs" of "-j,--jobs".
std::string long_name(const Setting& s);

// The command-line options that give `opt`'s recorded settings (scopes mesh and scene) to
// `lsnif convert` or `lsnif batch`, in the table's order and canonical form: what a batch
// records in its assets and what a Ninja file passes to every step, so that the keys its steps
// compute are the keys it planned. Threads, jobs and other run settings are not among them.
std::vector<std::string> settings_arguments(const ConvertOptions& opt);

// Applies options as settings_arguments writes them ("--seed", "3", "--fixed-model", ...) to
// `opt`; false with `error` ("--steps '0': ...") for an unknown option or a bad value.
bool apply_settings_arguments(const std::vector<std::string>& args, ConvertOptions& opt, std::string& error);

// The mesh-scope settings of `opt` in one line ("--preset smoke --seed 3 ..."): the settings
// part of every cache key, so that a setting that changes a result can never be left out of it.
std::string mesh_settings_key(const ConvertOptions& opt);
// The same of the report-scope settings: part of a mesh's record's cache key.
std::string report_settings_key(const ConvertOptions& opt);

// The manifest's `settings` object: every recorded row's value (schema/manifest.schema.json).
nlohmann::json settings_json(const ConvertOptions& opt);

}  // namespace lsnif::converter
