// The `lsnif` command. Only this file prints "error: ..." and chooses exit codes;
// everything it calls reports through return values.
#include <lsnif/converter/bench.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/format/container.hpp>

#include <CLI/CLI.hpp>

#include <cstdio>
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
