// `lsnif batch` (batch.hpp): inputs expanded, one convert() run with the cache, and the
// reports a CI system reads.
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

void fail(BatchResult& r, const std::string& error, BatchExit exit) {
    r.convert.errors.push_back(error);
    r.exit = exit;
}

void defer_errors(BatchResult& r, const std::string& step) {
    for (const std::string& e : r.input_errors)
        r.convert.warnings.push_back(e + " (the " + step + " will fail on it)");
    for (const std::string& e : r.convert.errors)
        r.convert.warnings.push_back(e + " (the " + step + " will fail on it)");
    r.input_errors.clear();
    r.convert.errors.clear();
    r.exit = BatchExit::ok;
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

}  // namespace lsnif::library
