// The `lsnif` command. Only this file prints "error: ..." and chooses exit codes;
// everything it calls reports through return values.
#include <lsnif/converter/bench.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/format/container.hpp>

#include <CLI/CLI.hpp>

#include <chrono>
#include <cstdio>

#include <unistd.h>
#include <iostream>

namespace {

int run_inspect(const std::string& path, bool as_json) {
    auto bytes = lsnif::format::read_file_bytes(path);
    if (!bytes) {
        std::fprintf(stderr, "error: %s\n", bytes.error().message.c_str());
        return 1;
    }
    const auto report = lsnif::converter::inspect_bytes(bytes.value(), path);
    if (as_json) std::cout << report.dump(2) << "\n";
    else std::cout << lsnif::converter::inspect_text(report);
    if (report.contains("error")) {
        if (as_json)  // text mode already printed the error line in the report
            std::fprintf(stderr, "error: %s: %s\n", path.c_str(),
                         report["error"]["message"].get<std::string>().c_str());
        return 1;
    }
    return 0;
}

int run_validate(const std::vector<std::string>& paths, bool as_json) {
    nlohmann::json all = nlohmann::json::array();
    bool ok = true;
    for (const std::string& p : paths) {
        const auto r = lsnif::converter::validate_file(p);
        ok = ok && r.valid();
        if (as_json) all.push_back(r.to_json());
        else (r.valid() ? std::cout : std::cerr) << r.to_text();
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
        if (e.stage != "train") {
            if (tty_ && drawn_) std::fputc('\n', stderr), drawn_ = false;
            if (new_stage) std::fprintf(stderr, "[%7.1fs] %-9s %s\n", now, e.stage.c_str(), e.mesh.c_str());
            return;
        }
        if (tty_) {
            const int width = 30, done = e.steps ? int(double(width) * e.step / e.steps) : 0;
            std::fprintf(stderr, "\r[%7.1fs] train     %-20.20s [%.*s%*s] %5u/%u loss %.4f ETA %4.0fs", now,
                         e.mesh.c_str(), done, "##############################", width - done, "", e.step, e.steps,
                         double(e.loss), e.eta_seconds);
            drawn_ = true;
        } else if (new_stage || now - last_line_ >= 5.0 || e.step == e.steps) {
            std::fprintf(stderr, "[%7.1fs] train     %s step %u/%u loss %.4f ETA %.0fs\n", now, e.mesh.c_str(), e.step,
                         e.steps, double(e.loss), e.eta_seconds);
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
    const auto r = lsnif::converter::convert(opt, [&](const lsnif::converter::ProgressEvent& e) { printer(e); });
    for (const auto& w : r.warnings) std::fprintf(stderr, "warning: %s\n", w.c_str());
    if (as_json) std::cout << r.report.dump(2) << "\n";
    else std::cout << lsnif::converter::convert_text(r);
    for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
    return r.ok() ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"lsnif: convert scenes into LSNIF neural intersection assets and check them"};
    app.set_version_flag("--version", std::string(LSNIF_VERSION_STRING));
    app.require_subcommand(1);

    std::string inspect_path;
    bool inspect_json = false;
    auto* inspect = app.add_subcommand("inspect", "Print header, sections, model dimensions and metadata of a .lsnif file");
    inspect->add_option("FILE", inspect_path, ".lsnif file")->required();
    inspect->add_flag("--json", inspect_json, "Machine-readable output");

    std::vector<std::string> validate_paths;
    bool validate_json = false;
    auto* validate = app.add_subcommand("validate", "Check .lsnif files completely; exit 0 only if all are valid");
    validate->add_option("FILE", validate_paths, ".lsnif files")->required();
    validate->add_flag("--json", validate_json, "Machine-readable output");

    lsnif::converter::ConvertOptions convert_opts;
    bool convert_json = false;
    auto* convert = app.add_subcommand("convert", "Convert scenes (glTF, OBJ, PLY, OFF, STL) into LSNIF assets and a manifest");
    convert->add_option("INPUT", convert_opts.inputs, "Scene files")->required();
    convert->add_option("-o,--output", convert_opts.outdir, "Output directory")->required();
    convert->add_flag("--json", convert_json, "Print a machine-readable report");
    convert->add_option("--seed", convert_opts.seed, "Random seed (sampling and training)");
    convert->add_option("--threads", convert_opts.threads, "Worker threads (0 = all cores)");
    convert->add_option("--preset", convert_opts.preset, "default, fast, quality or smoke (pipeline check)");
    convert->add_option("--complex", convert_opts.force_complex, "Force a mesh (by name) to become an LSNIF");
    convert->add_option("--simple", convert_opts.force_simple, "Force a mesh (by name) to stay BVH");
    convert->add_option("--gate-visibility", convert_opts.gate_min_visibility,
                        "Override the pooled held-out visibility accuracy an asset needs (0..1)")
        ->check(CLI::Range(0.0, 1.0));
    convert->add_option("--steps", convert_opts.steps, "Override the preset's training steps")
        ->check(CLI::Range(1u, 1000000u));
    convert->add_option("--batch", convert_opts.batch_size, "Override the preset's batch size (rays per step)")
        ->check(CLI::Range(64u, 1u << 20));
    convert->add_flag("--dry-run", convert_opts.dry_run,
                      "Import and classify only: print the plan (class, reasons, model size), write nothing");

    lsnif::converter::BenchOptions bench_opts;
    bool bench_json = false;
    auto* bench = app.add_subcommand("bench", "Throughput benchmarks (see BENCHMARKS.md)");
    bench->require_subcommand(1);
    bench->add_flag("--json", bench_json, "Machine-readable output");
    bench->add_option("--threads", bench_opts.threads, "Worker threads")->check(CLI::Range(1, 256));
    bench->add_option("--seconds", bench_opts.min_seconds, "Minimum seconds per measurement")->check(CLI::Range(0.01, 600.0));
    auto* bench_train = bench->add_subcommand("train", "Training samples/s (forward+backward+Adam) for batch 2^14..2^16, vs sgemm");
    auto* bench_infer = bench->add_subcommand("infer", "Inference rays/s through the network and with occupancy early-outs");
    for (auto* sub : {bench_train, bench_infer}) {
        sub->add_flag("--json", bench_json, "Machine-readable output");
        sub->add_option("--threads", bench_opts.threads, "Worker threads")->check(CLI::Range(1, 256));
        sub->add_option("--seconds", bench_opts.min_seconds, "Minimum seconds per measurement")->check(CLI::Range(0.01, 600.0));
    }

    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        return app.exit(e);
    }
    try {
        if (*inspect) return run_inspect(inspect_path, inspect_json);
        if (*validate) return run_validate(validate_paths, validate_json);
        if (*convert) {
            for (int i = 0; i < argc; ++i) convert_opts.command_line += (i ? " " : "") + std::string(argv[i]);
            return run_convert(convert_opts, convert_json);
        }
        if (*bench) {
            const auto report = *bench_train ? lsnif::converter::bench_train(bench_opts)
                                             : lsnif::converter::bench_infer(bench_opts);
            std::cout << (bench_json ? report.dump(2) + "\n" : lsnif::converter::bench_text(report));
            return 0;
        }
    } catch (const std::exception& e) {
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
    return 2;
}
