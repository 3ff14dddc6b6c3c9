// The `lsnif` command. Only this file prints "error: ..." and chooses exit codes;
// everything it calls reports through return values.
#include <lsnif/base/parallel.hpp>
#include <lsnif/cli/file_tools.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/eval/bench.hpp>
#include <lsnif/eval/eval.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/library/batch.hpp>

#include <CLI/CLI.hpp>

#include "cli_docs.hpp"

#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <deque>
#include <filesystem>
#include <set>

#include <unistd.h>
#include <iostream>
#include <map>

namespace {

// What --threads means for every subcommand that takes it.
constexpr const char* kThreadsHelp = "Worker threads (0: all cores)";

// "x,y,z,..." into exactly n finite floats.
bool parse_floats(const std::string& s, std::size_t n, float* out) {
    std::vector<float> v;
    std::size_t pos = 0;
    for (;;) {
        const std::size_t end = s.find(',', pos);
        const std::string part = s.substr(pos, end == std::string::npos ? std::string::npos : end - pos);
        char* stop = nullptr;
        const float x = std::strtof(part.c_str(), &stop);
        if (part.empty() || *stop != '\0' || !std::isfinite(x)) return false;
        v.push_back(x);
        if (end == std::string::npos) break;
        pos = end + 1;
    }
    if (v.size() != n) return false;
    std::copy(v.begin(), v.end(), out);
    return true;
}

int run_eval(lsnif::eval::EvalOptions opt, const std::string& camera, const std::string& light,
             const std::vector<std::string>& moves, bool as_json) {
    if (!camera.empty()) {
        float v[7] = {0, 0, 0, 0, 0, 0, 40.0f};
        if (!parse_floats(camera, 7, v) && !parse_floats(camera, 6, v)) {
            std::fprintf(stderr, "error: --camera '%s': expected ex,ey,ez,tx,ty,tz[,fov_deg]\n",
                         camera.c_str());
            return 2;
        }
        lsnif::render::Camera c;
        c.eye = {v[0], v[1], v[2]};
        c.target = {v[3], v[4], v[5]};
        c.fov_deg = v[6];
        opt.camera = c;
    }
    if (!light.empty()) {
        std::array<float, 3> l{};
        if (!parse_floats(light, 3, l.data())) {
            std::fprintf(stderr, "error: --light '%s': expected x,y,z\n", light.c_str());
            return 2;
        }
        opt.light = l;
    }
    for (const std::string& m : moves) {  // INSTANCE=m0,...,m11
        const std::size_t eq = m.find('=');
        std::array<float, 12> t{};
        char* stop = nullptr;
        const unsigned long idx = eq == std::string::npos ? 0 : std::strtoul(m.c_str(), &stop, 10);
        if (eq == std::string::npos || stop != m.c_str() + eq ||
            !parse_floats(m.substr(eq + 1), 12, t.data())) {
            std::fprintf(stderr,
                         "error: --instance-transform '%s': expected INDEX=m0,...,m11 (3x4 row-major)\n",
                         m.c_str());
            return 2;
        }
        opt.instance_transforms.emplace_back(std::uint32_t(idx), t);
    }
    const auto r = lsnif::eval::render_and_compare(opt);
    for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
    if (!r.ok()) return 1;
    if (as_json)
        std::cout << lsnif::eval::eval_report_json(*r.report).dump(2) << "\n";
    else
        std::cout << lsnif::eval::eval_report_text(*r.report);
    return 0;
}

int run_inspect(const std::string& path, bool as_json) {
    auto bytes = lsnif::format::read_file_bytes(path);
    if (!bytes) {
        std::fprintf(stderr, "error: %s\n", bytes.error().message.c_str());
        return 1;
    }
    const auto report = lsnif::cli::inspect_bytes(bytes.value(), path);
    if (as_json)
        std::cout << lsnif::cli::inspect_json(report).dump(2) << "\n";
    else
        std::cout << lsnif::cli::inspect_text(report);
    if (!report.ok()) {
        if (as_json)  // text mode already printed the error line in the report
            std::fprintf(stderr, "error: %s: %s\n", path.c_str(), report.error->message.c_str());
        return 1;
    }
    return 0;
}

int run_validate(const std::vector<std::string>& paths, bool as_json) {
    nlohmann::json all = nlohmann::json::array();
    bool ok = true;
    for (const std::string& p : paths) {
        const auto r = lsnif::cli::validate_file(p);
        ok = ok && r.valid();
        if (as_json)
            all.push_back(r.to_json());
        else
            (r.valid() ? std::cout : std::cerr) << r.to_text();
    }
    if (as_json) std::cout << nlohmann::json{{"valid", ok}, {"files", all}}.dump(2) << "\n";
    return ok ? 0 : 1;
}

// Progress on stderr: a redrawn bar on a terminal, plain periodic lines otherwise (logs, CI).
class ProgressPrinter {
public:
    ProgressPrinter() : tty_(::isatty(2) != 0), t0_(std::chrono::steady_clock::now()) {}
    ~ProgressPrinter() {
        if (tty_ && drawn_) std::fputc('\n', stderr);
    }
    void operator()(const lsnif::converter::ProgressEvent& e) {
        const double now = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
        const bool new_stage = e.stage != stage_ || e.mesh != mesh_;
        stage_ = e.stage;
        mesh_ = e.mesh;
        if (e.stage == "done") return;  // finished meshes are the commands' own lines
        if (e.stage != "train") {
            if (tty_ && drawn_) std::fputc('\n', stderr), drawn_ = false;
            if (new_stage) std::fprintf(stderr, "[%7.1fs] %-9s %s\n", now, e.stage.c_str(), e.mesh.c_str());
            return;
        }
        if (tty_) {
            const int width = 30, done = e.steps ? int(double(width) * e.step / e.steps) : 0;
            std::fprintf(stderr, "\r[%7.1fs] train     %-20.20s [%.*s%*s] %5u/%u loss %.4f ETA %4.0fs", now,
                         e.mesh.c_str(), done, "##############################", width - done, "", e.step,
                         e.steps, double(e.loss), e.eta_seconds);
            drawn_ = true;
        } else if (new_stage || now - last_line_ >= 5.0 || e.step == e.steps) {
            std::fprintf(stderr, "[%7.1fs] train     %s step %u/%u loss %.4f ETA %.0fs\n", now,
                         e.mesh.c_str(), e.step, e.steps, double(e.loss), e.eta_seconds);
            last_line_ = now;
        }
        std::fflush(stderr);
    }

private:
    bool tty_, drawn_ = false;
    std::chrono::steady_clock::time_point t0_;
    std::string stage_, mesh_;
    double last_line_ = -1e9;
};

int run_convert(lsnif::converter::ConvertOptions opt, bool as_json) {
    ProgressPrinter printer;
    const auto r =
        lsnif::converter::convert(opt, [&](const lsnif::converter::ProgressEvent& e) { printer(e); });
    for (const auto& w : r.warnings) std::fprintf(stderr, "warning: %s\n", w.c_str());
    if (r.usage_error) {
        for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
        return 2;
    }
    if (as_json)
        std::cout << lsnif::converter::convert_report_json(r).dump(2) << "\n";
    else
        std::cout << lsnif::converter::convert_text(r);
    for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
    return r.ok() ? 0 : 1;
}

// ---- subcommands: each registers its options on the app and runs once parsed ----------

struct InspectCommand {
    CLI::App* sub = nullptr;
    std::string path;
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand("inspect",
                                 "Print header, sections, model dimensions and metadata of a .lsnif file");
        sub->add_option("FILE", path, ".lsnif file")->type_name("FILE")->required();
        sub->add_flag("--json", json, "Machine-readable output");
    }
    int run() const { return run_inspect(path, json); }
};

struct ValidateCommand {
    CLI::App* sub = nullptr;
    std::vector<std::string> paths;
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand("validate", "Check .lsnif files completely; exit 0 only if all are valid");
        sub->add_option("FILE", paths, ".lsnif files")->type_name("FILE...")->required();
        sub->add_flag("--json", json, "Machine-readable output");
    }
    int run() const { return run_validate(paths, json); }
};

// Whether `arg` gives option `name` ("--cache", "--cache=DIR"; for a one-letter "-j" also
// "-j2"), and whether its value is the next argument.
bool gives_option(const std::string& arg, const std::string& name, bool takes_value, bool& value_follows) {
    value_follows = false;
    if (arg == name) return value_follows = takes_value, true;
    if (takes_value && arg.rfind(name + "=", 0) == 0) return true;
    return takes_value && name.size() == 2 && arg.size() > 2 && arg.rfind(name, 0) == 0 && arg[2] != '-';
}

// The command line recorded in each asset's metadata: without the output directory, --json and
// the run settings (threads, jobs, the cache: settings.hpp, SettingScope::run), which do not
// change the asset, and with the program by its name only, so the same conversion run into
// another directory or from another build gives the same bytes (the file name is already a
// content hash). --arithmetic is written as it runs here (machine on a CPU without bf16
// products is the canonical arithmetic). `lsnif batch` records its settings in a canonical
// form instead (batch.hpp, BatchOptions).
std::string recorded_command_line(int argc, char** argv, lsnif::converter::Arithmetic arithmetic) {
    std::vector<std::pair<std::string, bool>> dropped = {
        {"-o", true}, {"--output", true}, {"--json", false}, {"--arithmetic", true}};
    for (const lsnif::converter::Setting& s : lsnif::converter::settings_table()) {
        if (s.scope != lsnif::converter::SettingScope::run) continue;
        std::string names = s.names;
        for (std::size_t start = 0; start <= names.size();) {
            const std::size_t comma = std::min(names.find(',', start), names.size());
            dropped.emplace_back(names.substr(start, comma - start), s.value != nullptr);
            start = comma + 1;
        }
    }
    std::string line;
    for (int i = 0; i < argc; ++i) {
        const std::string a =
            i == 0 ? std::filesystem::path(argv[0]).filename().string() : std::string(argv[i]);
        bool drop = false, value_follows = false;
        for (const auto& [name, takes_value] : dropped)
            if (i > 0 && !drop && gives_option(a, name, takes_value, value_follows)) drop = true;
        if (value_follows) ++i;
        if (!drop) line += (line.empty() ? "" : " ") + a;
    }
    using lsnif::converter::arithmetic_id;
    if (arithmetic_id(arithmetic) != arithmetic_id(lsnif::converter::Arithmetic::canonical))
        line += " --arithmetic machine";
    return line;
}

// The settings `lsnif convert` and `lsnif batch` share, with the same meaning: every row of
// the settings table (lsnif/converter/settings.hpp), registered as CLI11 options that collect
// the text; finish() hands each value to its row, which checks it.
struct ConvertSettings {
    lsnif::converter::ConvertOptions opt;
    std::deque<std::vector<std::string>> values;  // per row: the values of a repeated setting, in order
    std::deque<std::string> value;                // per row: the value of a single one
    std::deque<std::int64_t> flags;               // per row: how often a flag was given
    std::vector<CLI::Option*> options;            // per row
    void add_to(CLI::App* sub) {
        for (const lsnif::converter::Setting& s : lsnif::converter::settings_table()) {
            const std::string help = std::string(s.help) + " [default: " + s.default_text + "]";
            std::int64_t& flag = flags.emplace_back(0);
            std::vector<std::string>& many = values.emplace_back();
            std::string& one = value.emplace_back();
            if (!s.value)
                options.push_back(sub->add_flag(s.names, flag, help));
            else if (s.repeated)  // one value per occurrence: `--complex a lib/` leaves lib/ an input
                options.push_back(
                    sub->add_option(s.names, many, help)->type_name(s.value)->allow_extra_args(false));
            else
                options.push_back(sub->add_option(s.names, one, help)->type_name(s.value));
        }
    }
    // The recorded settings (scopes mesh and scene) given on the command line, by name.
    std::vector<std::string> given_recorded() const {
        std::vector<std::string> names;
        const auto& table = lsnif::converter::settings_table();
        for (std::size_t k = 0; k < table.size(); ++k)
            if (table[k].scope != lsnif::converter::SettingScope::run && options[k]->count() > 0)
                names.push_back(lsnif::converter::long_name(table[k]));
        return names;
    }
    // Applies what was given, and the cache server's token from the environment (never from
    // the command line, where other users and logs see it); false (after printing the error)
    // is a usage error.
    bool finish() {
        if (const char* token = std::getenv("LSNIF_CACHE_TOKEN")) opt.cache_token = token;
        const auto& table = lsnif::converter::settings_table();
        for (std::size_t k = 0; k < table.size(); ++k) {
            const lsnif::converter::Setting& s = table[k];
            if (options[k]->count() == 0) continue;
            const std::vector<std::string> given = !s.value     ? std::vector<std::string>{""}
                                                   : s.repeated ? values[k]
                                                                : std::vector<std::string>{value[k]};
            for (const std::string& v : given) {
                std::string error, warning;
                const bool ok = s.set(opt, v, error, warning);
                if (!warning.empty()) std::fprintf(stderr, "warning: %s\n", warning.c_str());
                if (!ok) {
                    std::fprintf(stderr, "error: %s '%s': %s\n", lsnif::converter::long_name(s).c_str(),
                                 v.c_str(), error.c_str());
                    return false;
                }
            }
        }
        return true;
    }
};

struct ConvertCommand {
    CLI::App* sub = nullptr;
    ConvertSettings settings;
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand(
            "convert", "Convert scenes (glTF, OBJ, PLY, OFF, STL) into LSNIF assets and a manifest");
        sub->add_option("INPUT", settings.opt.inputs, "Scene files")->type_name("FILE...")->required();
        sub->add_option("-o,--output", settings.opt.outdir, "Output directory")->type_name("DIR")->required();
        sub->add_flag("--json", json, "Print a machine-readable report");
        settings.add_to(sub);
    }
    int run(int argc, char** argv) {
        if (!settings.finish()) return 2;
        settings.opt.command_line = recorded_command_line(argc, argv, settings.opt.arithmetic);
        return run_convert(settings.opt, json);
    }
};

struct BatchCommand {
    CLI::App* sub = nullptr;
    lsnif::library::BatchOptions batch;
    ConvertSettings settings;
    std::string shard;
    std::uint32_t task = 0;
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand(
            "batch",
            "Convert an asset library through a shared cache, for CI: one line per asset, "
            "JUnit XML, exit 0 (all converted or rightly BVH), 1 (some failed), 2 (usage)");
        sub->add_option("INPUT", batch.inputs,
                        "Scene files, directories (searched for scene files) or list files (one path per "
                        "line); none with --from-plan, whose plan names them")
            ->type_name("PATH...");
        sub->add_option("-o,--output", settings.opt.outdir, "Output directory (not with --plan)")
            ->type_name("DIR");
        sub->add_option("--junit", batch.junit_path, "Write JUnit XML here: one test case per asset")
            ->type_name("FILE");
        sub->add_option("--shard", shard,
                        "I/N: convert only this shard's share of the candidates (lsnif merge joins the N "
                        "output directories; with --from-plan, a share of the plan's tasks)")
            ->type_name("I/N");
        sub->add_flag("--json", json, "Print a machine-readable summary instead of the lines");
        sub->add_option("--ninja", batch.ninja_path,
                        "Plan only, and write a Ninja build file with one edge per object to convert "
                        "(run it with ninja -f FILE)")
            ->type_name("FILE");
        sub->add_option("--object", settings.opt.only_keys,
                        "Convert only the candidate with this cache key (a step of the --ninja file)")
            ->type_name("KEY")
            ->allow_extra_args(false);
        sub->add_option("--plan", batch.plan_path,
                        "Plan only, and write the library's plan here: every input with its SHA-256, every "
                        "object to convert as a task (0..N-1, costliest first) with its cache key")
            ->type_name("FILE");
        sub->add_option("--from-plan", batch.from_plan,
                        "Convert from a plan without planning the library again: with --task K one object, "
                        "with --shard I/N a share of the tasks, alone the whole library through the cache "
                        "(writing the manifest)")
            ->type_name("FILE");
        sub->add_option("--task", task, "The plan's task K (with --from-plan), e.g. $SLURM_ARRAY_TASK_ID")
            ->type_name("K");
        settings.add_to(sub);
    }
    // Why the options cannot go together; empty when they can.
    std::string conflict() const {
        const bool plan = !batch.plan_path.empty(), from = !batch.from_plan.empty();
        const bool has_task = sub->count("--task") > 0, has_shard = sub->count("--shard") > 0;
        if (plan + from + !batch.ninja_path.empty() + !settings.opt.only_keys.empty() > 1)
            return "--plan, --from-plan, --ninja and --object are different ways to run: give one";
        if (has_task && !from) return "--task needs --from-plan";
        if (has_task && has_shard) return "--task and --shard: give one";
        if (from && !batch.inputs.empty()) return "--from-plan: the plan names the inputs, give none";
        if (!from && batch.inputs.empty()) return "INPUT is required";
        if (!plan && settings.opt.outdir.empty()) return "--output is required";
        if (!plan && settings.opt.cache.empty())
            return "--cache is required: a directory or an http(s):// cache server";
        if (from)
            for (const std::string& name : settings.given_recorded())
                return "--from-plan: the plan fixes the settings, " + name +
                       " cannot change them (plan again)";
        return {};
    }
    int run() {
        if (!settings.finish()) return 2;
        if (const std::string why = conflict(); !why.empty()) {
            std::fprintf(stderr, "error: %s\n", why.c_str());
            return 2;
        }
        if (sub->count("--task") > 0) batch.task = task;
        std::string error;
        if (sub->count("--shard") > 0 &&
            !lsnif::library::parse_shard(shard, settings.opt.shard_index, settings.opt.shard_count, error)) {
            std::fprintf(stderr, "error: --shard '%s': %s\n", shard.c_str(), error.c_str());
            return 2;
        }
        settings.opt.reproducible_manifest = true;  // and batch() records its settings canonically
        batch.convert = settings.opt;
        batch.program = lsnif::converter::executable_path();
        std::set<std::string> streamed;
        ProgressPrinter printer;
        const auto r = lsnif::library::batch(
            batch, [&](const lsnif::converter::ProgressEvent& e) { printer(e); },
            [&](const std::string& line) {
                // One line per asset as soon as it is done (not with
                // --json, which prints one document at the end).
                streamed.insert(line);
                if (!json) std::cout << line << std::endl;
            });
        for (const auto& w : r.convert.warnings) std::fprintf(stderr, "warning: %s\n", w.c_str());
        if (r.exit == lsnif::library::BatchExit::usage) {
            for (const auto& e : r.convert.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
            return 2;
        }
        if (json) {
            std::cout << lsnif::library::batch_summary_json(r).dump(2) << "\n";
        } else if (!r.assets) {  // a plan (--ninja, --plan) or nothing to do
            for (const auto& line : r.lines) std::cout << line << "\n";
        } else {
            for (const auto& line : r.lines)  // what was not streamed: the inputs that failed
                if (!streamed.count(line)) std::cout << line << "\n";
            const auto& a = *r.assets;
            std::cout << a.lsnif << " LSNIF, " << a.bvh << " BVH, " << a.failed << " failed";
            if (const auto& c = r.convert.cache)
                std::cout << "; cache: " << c->hits << " found, " << c->stored << " stored, " << c->corrupt
                          << " corrupt";
            std::cout << "\n";
        }
        for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
        return int(r.exit);
    }
};

struct MergeCommand {
    CLI::App* sub = nullptr;
    std::vector<std::string> shards;
    std::string outdir, junit;
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand(
            "merge",
            "Join the output directories of lsnif batch --shard 1/N .. N/N into one, equal to "
            "a single run's");
        sub->add_option("SHARD_OUTDIR", shards, "Every shard's output directory")
            ->type_name("DIR...")
            ->required();
        sub->add_option("-o,--output", outdir, "Output directory")->type_name("DIR")->required();
        sub->add_option("--junit", junit,
                        "Write JUnit XML of the whole library here: one test case per asset")
            ->type_name("FILE");
        sub->add_flag("--json", json, "Print a machine-readable summary");
    }
    int run() const {
        const auto r = lsnif::library::merge(shards, outdir);
        for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
        if (json) std::cout << lsnif::library::merge_summary_json(shards, outdir, r).dump(2) << "\n";
        if (!r.errors.empty()) return 1;
        if (!junit.empty()) {
            if (const auto e =
                    lsnif::format::write_text_atomically(junit, lsnif::library::merge_junit_xml(r))) {
                std::fprintf(stderr, "error: %s\n", e.message.c_str());
                return 1;
            }
        }
        if (!json)
            std::cout << "merged " << shards.size() << " shards: " << r.meshes.size() << " meshes into "
                      << outdir << "/manifest.json\n";
        return 0;
    }
};

// --arithmetic NAME and its shorthand --fp32: the network arithmetic LSNIF models use
// (lsnif_set_arithmetic; default auto, what lsnif_open picks).
void add_arithmetic_options(CLI::App* s, lsnif_arithmetic& arithmetic) {
    const std::map<std::string, lsnif_arithmetic> names{{"auto", LSNIF_ARITHMETIC_AUTO},
                                                        {"fp32", LSNIF_ARITHMETIC_FP32},
                                                        {"bf16", LSNIF_ARITHMETIC_BF16},
                                                        {"int8", LSNIF_ARITHMETIC_INT8}};
    auto* named =
        s->add_option("--arithmetic", arithmetic,
                      "LSNIF network arithmetic: auto (default: int8 where the CPU has AVX-512 VNNI, "
                      "else bf16 where it has AVX-512 BF16, else fp32), fp32 (the reference), "
                      "bf16 or int8 (each falls back where the CPU lacks it)")
            ->transform(CLI::CheckedTransformer(names, CLI::ignore_case))
            ->type_name("auto|fp32|bf16|int8")
            ->default_str("auto");
    s->add_flag_callback(
         "--fp32", [&arithmetic] { arithmetic = LSNIF_ARITHMETIC_FP32; }, "Same as --arithmetic fp32")
        ->excludes(named);
}

struct EvalCommand {
    CLI::App* sub = nullptr;
    lsnif::eval::EvalOptions opt;
    std::string camera, light;
    std::vector<std::string> moves;
    std::uint32_t old_repeats = 3;  // --timing-repeats
    bool json = false, objects = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand("eval",
                                 "Render reference (Embree) and hybrid (BVH + LSNIF) images of a converted "
                                 "scene; compare them with FLIP and PSNR");
        sub->add_option("OUTDIR", opt.outdir, "A `lsnif convert` output directory")
            ->type_name("DIR")
            ->required();
        sub->add_option("--source", opt.sources, "The converted inputs (default: the paths in the manifest)")
            ->type_name("FILE...");
        sub->add_option("--images", opt.images_dir, "Where PNGs and report.json go (default OUTDIR/eval)")
            ->type_name("DIR");
        sub->add_option("--camera", camera,
                        "Eye and target, optionally the vertical field of view (default frames the scene)")
            ->type_name("EX,EY,EZ,TX,TY,TZ[,FOV]");
        sub->add_option("--light", light, "Point light position (default above the scene)")
            ->type_name("X,Y,Z");
        sub->add_option("--instance-transform", moves,
                        "Place instance INDEX elsewhere: a 3x4 row-major transform")
            ->type_name("INDEX=M0,...,M11");
        sub->add_option("--width", opt.width, "Image width")->check(CLI::Range(1u, 8192u))->type_name("N");
        sub->add_option("--height", opt.height, "Image height")->check(CLI::Range(1u, 8192u))->type_name("N");
        sub->add_option("--surface-tmin", opt.surface_tmin_voxels,
                        "Hybrid only: secondary rays leaving an LSNIF object start this many of its voxels "
                        "from the surface (0 = off; docs/model.md)")
            ->check(CLI::Range(0.0f, 4.0f))
            ->type_name("VOXELS");
        sub->add_option("--escape-points", opt.escape_points,
                        "Rays that start inside an occupied voxel of an asset and meet at most N of them, "
                        "one run of face neighbours, miss it without the network (0 = off; default: the "
                        "limit conversion chose for each asset; docs/model.md \"The escape rule\")")
            ->check(CLI::Range(0u, 64u))
            ->type_name("N");
        sub->add_option(
               "--enclosed-rule", opt.enclosed_rule,
               "Occlusion rays that pass from an asset's occupied voxels into the space they shut in "
               "are occluded without the network: on (default) or off (docs/model.md \"The enclosed "
               "rule\")")
            ->transform(CLI::CheckedTransformer(std::map<std::string, bool>{{"on", true}, {"off", false}}))
            ->type_name("on|off")
            ->default_str("on");
        sub->add_option(
               "--embree-route", opt.embree_route,
               "How both tracers' Embree part traces: packets16 (16 consecutive rays per "
               "rtcIntersect16/rtcOccluded16 call) or single (one ray per call; docs/eval.md \"Timing\")")
            ->transform(CLI::CheckedTransformer(std::map<std::string, lsnif::render::EmbreeRoute>{
                {"packets16", lsnif::render::EmbreeRoute::packets16},
                {"single", lsnif::render::EmbreeRoute::single}}))
            ->type_name("packets16|single")
            ->default_str("packets16");
        sub->add_option("--repeats", opt.timing_repeats,
                        "Trace each row's secondary rays this many times per tracer, alternating, and keep "
                        "each tracer's fastest for the time ratio (docs/eval.md \"Timing\")")
            ->check(CLI::Range(1u, 100u))
            ->type_name("N");
        // The earlier name, kept for scripts that use it.
        sub->add_option("--timing-repeats", old_repeats, "Deprecated: --repeats")
            ->check(CLI::Range(1u, 100u))
            ->type_name("N");
        sub->add_option("--ao-samples", opt.ao_samples, "Ambient-occlusion rays per pixel")
            ->check(CLI::Range(1u, 1024u))
            ->type_name("N");
        sub->add_option("--threads", opt.threads, kThreadsHelp)->check(CLI::Range(0, 4096))->type_name("N");
        add_arithmetic_options(sub, opt.arithmetic);
        sub->add_flag(
            "--objects", objects,
            "Instead of the scene: every converted object alone on a floor, in the views of the "
            "conversion's visual check, through its asset (IMAGES/objects/, docs/model.md \"Judged by "
            "how it looks\")");
        sub->add_flag("--json", json, "Print the report as JSON");
    }
    int run() {
        if (objects) return run_objects();
        if (sub->count("--timing-repeats") > 0) {
            std::fprintf(stderr, "warning: --timing-repeats is deprecated: use --repeats\n");
            if (sub->count("--repeats") == 0) opt.timing_repeats = old_repeats;
        }
        return run_eval(opt, camera, light, moves, json);
    }
    int run_objects() const {
        const auto r = lsnif::eval::render_objects(opt);
        for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
        if (!r.ok()) return 1;
        if (json)
            std::cout << lsnif::eval::objects_report_json(*r.report).dump(2) << "\n";
        else
            std::cout << lsnif::eval::objects_report_text(*r.report);
        return 0;
    }
};

struct BenchCommand {
    CLI::App* sub = nullptr;
    CLI::App *train = nullptr, *infer = nullptr, *memory = nullptr, *rays = nullptr, *convert = nullptr;
    lsnif::eval::BenchOptions opt;
    lsnif::eval::SceneBenchOptions scene;
    lsnif::converter::ConvertOptions convert_opt;
    std::uint32_t threads = 0;  // --threads of every bench subcommand but convert
    bool json = false;
    void add_to(CLI::App& app) {
        sub = app.add_subcommand("bench", "Throughput benchmarks (see BENCHMARKS.md)");
        sub->require_subcommand(1);
        add_common(sub);
        train = sub->add_subcommand(
            "train", "Training samples/s (forward+backward+Adam) for batch 2^14..2^16, vs sgemm");
        infer = sub->add_subcommand("infer",
                                    "Inference rays/s through the network and with occupancy early-outs");
        memory = sub->add_subcommand(
            "memory", "Resident and file bytes per complex object vs Embree's BVH and a compressed BVH8");
        rays = sub->add_subcommand(
            "rays", "LSNIF inference vs rtcIntersect1/rtcIntersect16 on the same rays, per object");
        for (auto* s : {memory, rays}) {
            s->add_option("OUTDIR", scene.outdir, "A `lsnif convert` output directory")
                ->type_name("DIR")
                ->required();
            s->add_option("--source", scene.sources, "The converted inputs (default: the manifest's paths)")
                ->type_name("FILE...");
            s->add_flag("--json", json, "Machine-readable output");
            s->add_option("--threads", threads, kThreadsHelp)->check(CLI::Range(0, 4096))->type_name("N");
        }
        rays->add_option("--rays", scene.rays, "Rays per object")
            ->check(CLI::Range(1024ull, 1ull << 26))
            ->type_name("N");
        rays->add_option("--repeats", scene.repeats, "Best of N")
            ->check(CLI::Range(1u, 100u))
            ->type_name("N");
        add_arithmetic_options(rays, scene.arithmetic);
        convert = sub->add_subcommand("convert",
                                      "Convert INPUT... into OUTDIR and print the wall time split by stage");
        convert->add_option("INPUT", convert_opt.inputs, "Scene files")->type_name("FILE...")->required();
        convert->add_option("-o,--output", convert_opt.outdir, "Output directory")
            ->type_name("DIR")
            ->required();
        convert->add_option("--preset", convert_opt.preset, "Preset")->type_name("NAME");
        convert->add_option("--threads", convert_opt.threads, kThreadsHelp)
            ->check(CLI::Range(0, 4096))
            ->type_name("N");
        convert
            ->add_option("--complex", convert_opt.force_complex, "Force a mesh (by name) to become an LSNIF")
            ->type_name("NAME");
        convert->add_flag("--json", json, "Machine-readable output");
        for (auto* s : {train, infer}) add_common(s);
    }
    // --json, --threads and --seconds of bench train|infer, accepted before or after the
    // subcommand's name.
    void add_common(CLI::App* s) {
        s->add_flag("--json", json, "Machine-readable output");
        s->add_option("--threads", threads, kThreadsHelp)->check(CLI::Range(0, 4096))->type_name("N");
        s->add_option("--seconds", opt.min_seconds, "Minimum seconds per measurement")
            ->check(CLI::Range(0.01, 600.0))
            ->type_name("SECONDS");
    }
    int run() {
        // One meaning of --threads everywhere: 0 (the default) is every core.
        opt.threads = scene.threads = lsnif::base::resolve_threads(threads);
        // Each result through its own writers: bench_json's for --json, else bench_text's.
        const auto print = [&](const auto& bench) {
            std::cout << (json ? lsnif::eval::bench_json(bench).dump(2) + "\n"
                               : lsnif::eval::bench_text(bench));
            return 0;
        };
        const auto print_or_fail = [&](const auto& result) {
            if (!result) {
                std::fprintf(stderr, "error: %s\n", result.error().c_str());
                return 1;
            }
            return print(*result);
        };
        if (*train) return print(lsnif::eval::bench_train(opt));
        if (*infer) return print(lsnif::eval::bench_infer(opt));
        if (*memory) return print_or_fail(lsnif::eval::bench_memory(scene));
        if (*rays) return print_or_fail(lsnif::eval::bench_rays(scene));
        return print_or_fail(lsnif::eval::bench_convert(convert_opt));
    }
};

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"lsnif: convert scenes into LSNIF neural intersection assets and check them"};
    // Every option's --help line shows its default (the settings table's rows say theirs in
    // words: ConvertSettings).
    app.option_defaults()->always_capture_default();
    // Usage errors CLI11 finds (a value out of range, an unknown option) read like ours:
    // "error: ..." on one line, then where to look.
    app.failure_message([](const CLI::App*, const CLI::Error& e) {
        return "error: " + std::string(e.what()) + "\nRun with --help for more information.\n";
    });
    // The tool's identity keys the cache (docs/pipeline.md "Cache keys"): CI keys its cache
    // action on this output (examples/ci/lsnif-ci cache-key).
    app.set_version_flag("--version", [] {
        const auto& id = lsnif::converter::tool_identity();
        return "lsnif " + id.version + "\nidentity " + id.digest + "\n  sources " + id.sources +
               "\n  compiler " + id.compiler + (id.flags.empty() ? "" : " (" + id.flags + ")") +
               "\n  embree " + id.embree + ", zstd " + id.zstd + ", nlohmann_json " + id.json +
               "\n  arithmetic " + lsnif::converter::arithmetic_id(lsnif::converter::Arithmetic::canonical);
    });
    app.require_subcommand(1);
    InspectCommand inspect;
    ValidateCommand validate;
    ConvertCommand convert;
    BatchCommand batch;
    MergeCommand merge;
    EvalCommand eval;
    BenchCommand bench;
    inspect.add_to(app);
    validate.add_to(app);
    convert.add_to(app);
    batch.add_to(app);
    merge.add_to(app);
    eval.add_to(app);
    bench.add_to(app);
    // The command line described from itself (cli_docs.hpp): README tables, man page, completion.
    if (argc == 2 && std::string(argv[1]) == "--help-markdown") {
        std::cout << lsnif::cli::markdown_reference(app);
        return 0;
    }
    if (argc == 2 && std::string(argv[1]) == "--help-man") {
        std::cout << lsnif::cli::man_page(app, lsnif::converter::tool_identity().version);
        return 0;
    }
    if (argc == 2 && std::string(argv[1]) == "--completion-bash") {
        std::cout << lsnif::cli::bash_completion(app);
        return 0;
    }
    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        // CLI11 prints the message; its own codes (105, 106, ...) become our one usage code,
        // 2, documented for every command (--help and --version stay 0).
        return app.exit(e) == 0 ? 0 : 2;
    }
    if (const std::string& isa = lsnif::format::isa_cap_error(); !isa.empty()) {
        std::fprintf(stderr, "error: %s\n", isa.c_str());
        return 2;
    }
    try {
        if (*inspect.sub) return inspect.run();
        if (*validate.sub) return validate.run();
        if (*convert.sub) return convert.run(argc, argv);
        if (*batch.sub) return batch.run();
        if (*merge.sub) return merge.run();
        if (*eval.sub) return eval.run();
        if (*bench.sub) return bench.run();
    } catch (const std::exception& e) {
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
    return 2;
}
