// Plan once (docs/pipeline.md "Plan once"): `lsnif batch --plan FILE` writes a library's plan,
// `--from-plan FILE --task K | --shard I/N` converts part of it without planning the library
// again, and `--from-plan FILE` alone assembles the manifest through the cache.
#include <lsnif/cache/cache.hpp>
#include <lsnif/converter/json_reader.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/library/batch.hpp>
#include "batch_internal.hpp"

#include <fstream>
#include <set>

namespace lsnif::library {

using converter::ConvertOptions;
using converter::ConvertProgress;
using converter::json_reader::Reader;
using nlohmann::json;
using namespace detail;

json plan_json(const LibraryPlan& plan) {
    json inputs = json::array(), tasks = json::array();
    for (const PlannedInput& in : plan.inputs) inputs.push_back({{"path", in.path}, {"sha256", in.sha256}});
    for (std::size_t k = 0; k < plan.tasks.size(); ++k) {
        const PlannedTask& t = plan.tasks[k];
        tasks.push_back({{"task", k},
                         {"key", t.key},
                         {"input", t.input},
                         {"mesh", t.mesh},
                         {"estimated_ms", t.estimated_ms}});
    }
    return {{"format", kPlanFormat},
            {"tool", {{"name", "lsnif"}, {"version", plan.version}, {"identity", plan.identity}}},
            {"settings", plan.settings},
            {"inputs", inputs},
            {"tasks", tasks}};
}

base::Result<LibraryPlan, std::string> plan_from_json(const json& j) {
    LibraryPlan plan;
    Reader r(j, "");
    std::string format;
    r.read("format", format);
    if (r.ok() && format != kPlanFormat) r.fail("format", format + ", this lsnif reads " + kPlanFormat);
    r.nested("tool", [&](Reader& t) {
        t.read("version", plan.version);
        t.read("identity", plan.identity);
    });
    r.read("settings", plan.settings);
    r.records("inputs", plan.inputs, [](Reader& in, PlannedInput& p) {
        in.read("path", p.path);
        in.read("sha256", p.sha256);
    });
    r.records("tasks", plan.tasks, [&](Reader& t, PlannedTask& p) {
        std::size_t task = 0;
        t.read("task", task);
        t.read("key", p.key);
        t.read("input", p.input);
        t.read("mesh", p.mesh);
        t.read("estimated_ms", p.estimated_ms);
        if (t.ok() && task != plan.tasks.size() - 1) t.fail("task", "not the task's index");
        if (t.ok() && p.input >= plan.inputs.size()) t.fail("input", "no such input");
        if (t.ok() && !cache::valid_key(p.key)) t.fail("key", "not a cache key");
    });
    if (!r.ok()) return r.error();
    return plan;
}

namespace {

// SHA-256 of a file's bytes, or nothing (and `error`) when it cannot be read.
std::optional<std::string> file_sha256(const std::string& path, std::string& error) {
    std::ifstream f(path, std::ios::binary);
    if (!f) {
        error = path + ": cannot read";
        return std::nullopt;
    }
    cache::Sha256 h;
    std::vector<char> buffer(1 << 20);
    while (f) {
        f.read(buffer.data(), std::streamsize(buffer.size()));
        h.update({reinterpret_cast<const std::uint8_t*>(buffer.data()), std::size_t(f.gcount())});
    }
    if (f.bad()) {
        error = path + ": read error";
        return std::nullopt;
    }
    return h.hex();
}

// The plan in `path`, or nothing (r failed) when it cannot be read or is not a plan.
std::optional<LibraryPlan> read_plan(const std::string& path, BatchResult& r) {
    std::ifstream f(path);
    if (!f) return fail(r, path + ": cannot read the plan"), std::nullopt;
    const json doc = json::parse(f, nullptr, false);
    auto plan = plan_from_json(doc);
    if (!plan) return fail(r, path + ": not an lsnif plan: " + plan.error()), std::nullopt;
    return std::move(*plan);
}

// Why the plan cannot be used by this lsnif, or for these inputs: another build, or an
// input whose bytes changed since it was planned (its keys would be other keys). Empty when
// it can. `inputs`: the indexes to check.
std::string plan_problem(const std::string& path, const LibraryPlan& plan,
                         const std::set<std::size_t>& inputs) {
    if (plan.identity != converter::tool_identity().digest)
        return path + ": planned by another lsnif build (identity " + plan.identity + ", this one is " +
               converter::tool_identity().digest + "): plan again";
    for (std::size_t i : inputs) {
        std::string error;
        const auto now = file_sha256(plan.inputs[i].path, error);
        if (!now) return error + " (planned in " + path + "): plan again";
        if (*now != plan.inputs[i].sha256)
            return plan.inputs[i].path + ": changed since it was planned in " + path + ": plan again";
    }
    return {};
}

// The tasks a --from-plan run converts: one (--task), a shard's share, or every task.
std::optional<std::vector<std::size_t>> selected_tasks(const BatchOptions& options, const LibraryPlan& plan,
                                                       BatchResult& r) {
    std::vector<std::size_t> chosen;
    const ConvertOptions& c = options.convert;
    if (options.task) {
        if (*options.task >= plan.tasks.size())
            return fail(r,
                        "--task " + std::to_string(*options.task) + ": the plan has " +
                            std::to_string(plan.tasks.size()) + " tasks (0 to " +
                            std::to_string(plan.tasks.size()) + " - 1)",
                        BatchExit::usage),
                   std::nullopt;
        chosen.push_back(*options.task);
    } else if (c.shard_count > 0) {
        std::vector<std::uint64_t> costs;
        for (const PlannedTask& t : plan.tasks) costs.push_back(t.estimated_ms);
        const std::vector<std::uint32_t> shard = converter::deal_to_shards(costs, c.shard_count);
        for (std::size_t k = 0; k < shard.size(); ++k)
            if (shard[k] + 1 == c.shard_index) chosen.push_back(k);
    } else {
        for (std::size_t k = 0; k < plan.tasks.size(); ++k) chosen.push_back(k);
    }
    return chosen;
}

}  // namespace

namespace detail {

void write_plan(const BatchOptions& options, const ConvertProgress& progress, BatchResult& r) {
    const auto objects = plan_library(options.convert, progress, r);
    if (!objects) return;
    LibraryPlan plan;
    plan.version = LSNIF_VERSION_STRING;
    plan.identity = converter::tool_identity().digest;
    plan.settings = converter::settings_arguments(options.convert);
    for (const std::string& scene : r.scenes) {
        std::string error;
        const auto sha = file_sha256(scene, error);
        if (!sha) return fail(r, error);
        plan.inputs.push_back({scene, *sha});
    }
    for (const PlannedObject& o : *objects) plan.tasks.push_back({o.key, o.input, o.mesh, o.estimated_ms});
    if (const format::Error e =
            format::write_text_atomically(options.plan_path, plan_json(plan).dump(2) + "\n"))
        return fail(r, e.message);
    r.lines.push_back("planned  " + std::to_string(plan.tasks.size()) + " tasks (0 to " +
                      std::to_string(plan.tasks.size()) + " - 1) over " + std::to_string(plan.inputs.size()) +
                      " inputs: " + options.plan_path);
    // Inputs that cannot be imported fail in the assembly step, where CI sees them.
    defer_errors(r, "assembly");
}

void run_from_plan(const BatchOptions& options, const ConvertProgress& progress,
                   const std::function<void(const std::string&)>& on_line, BatchResult& r) {
    const auto plan = read_plan(options.from_plan, r);
    if (!plan) return;
    const auto chosen = selected_tasks(options, *plan, r);
    if (!chosen) return;
    const bool assembly = !options.task && options.convert.shard_count == 0;
    std::set<std::size_t> inputs;
    for (std::size_t k : *chosen) inputs.insert(plan->tasks[k].input);
    if (assembly)
        for (std::size_t i = 0; i < plan->inputs.size(); ++i) inputs.insert(i);
    if (std::string why = plan_problem(options.from_plan, *plan, inputs); !why.empty()) return fail(r, why);
    ConvertOptions c = options.convert;
    c.shard_count = c.shard_index = 0;  // the plan's tasks are the shares
    std::string error;
    if (!converter::apply_settings_arguments(plan->settings, c, error))
        return fail(r, options.from_plan + ": its settings: " + error);
    for (std::size_t i : inputs) r.scenes.push_back(plan->inputs[i].path);
    if (!assembly) {
        if (chosen->empty()) {
            r.lines.push_back("nothing  to convert: this shard has no task of " + options.from_plan);
            return;
        }
        for (std::size_t k : *chosen) c.only_keys.push_back(plan->tasks[k].key);
    }
    convert_library(options, c, progress, on_line, r);
}

}  // namespace detail

}  // namespace lsnif::library
