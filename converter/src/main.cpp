// The `lsnif` command. Only this file prints "error: ..." and chooses exit codes;
// everything it calls reports through return values.
#include <lsnif/converter/bench.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/eval.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/format/container.hpp>

#include <CLI/CLI.hpp>

#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

#include <unistd.h>
#include <iostream>

namespace {

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

int run_eval(lsnif::converter::EvalOptions opt, const std::string& camera, const std::string& light,
             const std::vector<std::string>& moves, bool as_json) {
    if (!camera.empty()) {
        float v[7] = {0, 0, 0, 0, 0, 0, 40.0f};
        if (!parse_floats(camera, 7, v) && !parse_floats(camera, 6, v)) {
            std::fprintf(stderr, "error: --camera '%s': expected ex,ey,ez,tx,ty,tz[,fov_deg]\n",
                         camera.c_str());
            return 2;
        }
        lsnif::converter::EvalCamera c;
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
    const auto r = lsnif::converter::render_and_compare(opt);
    for (const auto& e : r.errors) std::fprintf(stderr, "error: %s\n", e.c_str());
    if (!r.ok()) return 1;
    if (as_json) {
        std::cout << r.report.dump(2) << "\n";
    } else {
        const auto& j = r.report;
        std::printf("rendered %ux%u, %zu instances (%zu through LSNIF), images in %s\n",
                    j["width"].get<unsigned>(), j["height"].get<unsigned>(),
                    j["instances"].get<std::size_t>(), j["lsnif_instances"].get<std::size_t>(),
                    j["images_dir"].get<std::string>().c_str());
        for (const auto& [name, v] : j["images"].items())
            std::printf("  %-10s FLIP mean %.4f (median %.4f, p95 %.4f)  PSNR %s dB\n", name.c_str(),
                        v["flip_mean"].get<double>(), v["flip_median"].get<double>(),
                        v["flip_p95"].get<double>(),
                        v["psnr_db"].is_null() ? "inf" : std::to_string(v["psnr_db"].get<double>()).c_str());
        std::printf("  overall    FLIP mean %.4f; secondary-ray time hybrid/reference %.2f\n",
                    j["flip_mean"].get<double>(), j["secondary_time_ratio"].get<double>());
    }
    return 0;
}

int run_inspect(const std::string& path, bool as_json) {
    auto bytes = lsnif::format::read_file_bytes(path);
    if (!bytes) {
        std::fprintf(stderr, "error: %s\n", bytes.error().message.c_str());
        return 1;
    }
    const auto report = lsnif::converter::inspect_bytes(bytes.value(), path);
    if (as_json)
        std::cout << report.dump(2) << "\n";
    else
        std::cout << lsnif::converter::inspect_text(report);
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
    if (as_json)
        std::cout << r.report.dump(2) << "\n";
    else
        std::cout << lsnif::converter::convert_text(r);
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
    auto* inspect = app.add_subcommand(
        "inspect", "Print header, sections, model dimensions and metadata of a .lsnif file");
    inspect->add_option("FILE", inspect_path, ".lsnif file")->required();
    inspect->add_flag("--json", inspect_json, "Machine-readable output");

    std::vector<std::string> validate_paths;
    bool validate_json = false;
    auto* validate =
        app.add_subcommand("validate", "Check .lsnif files completely; exit 0 only if all are valid");
    validate->add_option("FILE", validate_paths, ".lsnif files")->required();
    validate->add_flag("--json", validate_json, "Machine-readable output");

    lsnif::converter::ConvertOptions convert_opts;
    bool convert_json = false;
    auto* convert = app.add_subcommand(
        "convert", "Convert scenes (glTF, OBJ, PLY, OFF, STL) into LSNIF assets and a manifest");
    convert->add_option("INPUT", convert_opts.inputs, "Scene files")->required();
    convert->add_option("-o,--output", convert_opts.outdir, "Output directory")->required();
    convert->add_flag("--json", convert_json, "Print a machine-readable report");
    convert->add_option("--seed", convert_opts.seed, "Random seed (sampling and training)");
    convert->add_option("--threads", convert_opts.threads, "Worker threads (0 = all cores)");
    convert->add_option("--preset", convert_opts.preset, "default, fast, quality or smoke (pipeline check)");
    convert->add_option("--complex", convert_opts.force_complex, "Force a mesh (by name) to become an LSNIF");
    convert->add_option("--simple", convert_opts.force_simple, "Force a mesh (by name) to stay BVH");
    convert
        ->add_option("--gate-visibility", convert_opts.gate_min_visibility,
                     "Override the pooled held-out visibility accuracy an asset needs (0..1)")
        ->check(CLI::Range(0.0, 1.0));
    convert->add_option("--steps", convert_opts.steps, "Override the preset's training steps")
        ->check(CLI::Range(1u, 1000000u));
    convert
        ->add_option("--batch", convert_opts.batch_size, "Override the preset's batch size (rays per step)")
        ->check(CLI::Range(64u, 1u << 20));
    convert
        ->add_option("--log2-table", convert_opts.log2_table_size,
                     "Override T = 2^N hash-table rows per level")
        ->check(CLI::Range(10u, 24u));
    convert->add_option("--max-points", convert_opts.max_points, "Override H, voxel entry points per ray")
        ->check(CLI::Range(1u, 64u));
    convert->add_option("--grid", convert_opts.grid_resolution, "Override V, occupancy grid resolution")
        ->check(CLI::Range(4u, 256u));
    convert->add_option("--hidden", convert_opts.hidden_width, "Override the hidden layers' width")
        ->check(CLI::Range(16u, 512u));
    convert->add_flag("--dry-run", convert_opts.dry_run,
                      "Import and classify only: print the plan (class, reasons, model size), write nothing");

    lsnif::converter::EvalOptions eval_opts;
    std::string eval_camera, eval_light;
    std::vector<std::string> eval_moves;
    bool eval_json = false;
    auto* evalc =
        app.add_subcommand("eval",
                           "Render reference (Embree) and hybrid (BVH + LSNIF) images of a converted "
                           "scene; compare them with FLIP and PSNR");
    evalc->add_option("OUTDIR", eval_opts.outdir, "A `lsnif convert` output directory")->required();
    evalc->add_option("--source", eval_opts.sources,
                      "The converted inputs (default: the paths in the manifest)");
    evalc->add_option("--images", eval_opts.images_dir,
                      "Where PNGs and report.json go (default OUTDIR/eval)");
    evalc->add_option("--camera", eval_camera, "ex,ey,ez,tx,ty,tz[,fov_deg] (default frames the scene)");
    evalc->add_option("--light", eval_light, "Point light x,y,z (default above the scene)");
    evalc->add_option("--instance-transform", eval_moves,
                      "INDEX=m0,...,m11: place an instance elsewhere (3x4 row-major)");
    evalc->add_option("--width", eval_opts.width, "Image width")->check(CLI::Range(1u, 8192u));
    evalc->add_option("--height", eval_opts.height, "Image height")->check(CLI::Range(1u, 8192u));
    evalc->add_option("--ao-samples", eval_opts.ao_samples, "Ambient-occlusion rays per pixel")
        ->check(CLI::Range(1u, 1024u));
    evalc->add_option("--threads", eval_opts.threads, "Worker threads (0 = all cores)");
    evalc->add_flag("--json", eval_json, "Print the report as JSON");

    lsnif::converter::BenchOptions bench_opts;
    bool bench_json = false;
    auto* bench = app.add_subcommand("bench", "Throughput benchmarks (see BENCHMARKS.md)");
    bench->require_subcommand(1);
    bench->add_flag("--json", bench_json, "Machine-readable output");
    bench->add_option("--threads", bench_opts.threads, "Worker threads")->check(CLI::Range(1, 256));
    bench->add_option("--seconds", bench_opts.min_seconds, "Minimum seconds per measurement")
        ->check(CLI::Range(0.01, 600.0));
    auto* bench_train = bench->add_subcommand(
        "train", "Training samples/s (forward+backward+Adam) for batch 2^14..2^16, vs sgemm");
    auto* bench_infer =
        bench->add_subcommand("infer", "Inference rays/s through the network and with occupancy early-outs");
    lsnif::converter::SceneBenchOptions scene_bench;
    auto* bench_memory = bench->add_subcommand(
        "memory", ".lsnif bytes per complex object vs Embree's BVH and a BVH8 estimate");
    auto* bench_rays = bench->add_subcommand(
        "rays", "LSNIF inference vs rtcIntersect1/rtcIntersect16 on the same rays, per object");
    for (auto* sub : {bench_memory, bench_rays}) {
        sub->add_option("OUTDIR", scene_bench.outdir, "A `lsnif convert` output directory")->required();
        sub->add_option("--source", scene_bench.sources,
                        "The converted inputs (default: the manifest's paths)");
        sub->add_flag("--json", bench_json, "Machine-readable output");
        sub->add_option("--threads", scene_bench.threads, "Worker threads")->check(CLI::Range(1, 256));
    }
    bench_rays->add_option("--rays", scene_bench.rays, "Rays per object")
        ->check(CLI::Range(1024ull, 1ull << 26));
    bench_rays->add_option("--repeats", scene_bench.repeats, "Best of N")->check(CLI::Range(1u, 100u));
    lsnif::converter::ConvertOptions bench_convert_opts;
    auto* bench_conv = bench->add_subcommand(
        "convert", "Convert INPUT... into OUTDIR and print the wall time split by stage");
    bench_conv->add_option("INPUT", bench_convert_opts.inputs, "Scene files")->required();
    bench_conv->add_option("-o,--output", bench_convert_opts.outdir, "Output directory")->required();
    bench_conv->add_option("--preset", bench_convert_opts.preset, "Preset");
    bench_conv->add_option("--threads", bench_convert_opts.threads, "Worker threads (0 = all cores)");
    bench_conv->add_option("--complex", bench_convert_opts.force_complex,
                           "Force a mesh (by name) to become an LSNIF");
    bench_conv->add_flag("--json", bench_json, "Machine-readable output");
    for (auto* sub : {bench_train, bench_infer}) {
        sub->add_flag("--json", bench_json, "Machine-readable output");
        sub->add_option("--threads", bench_opts.threads, "Worker threads")->check(CLI::Range(1, 256));
        sub->add_option("--seconds", bench_opts.min_seconds, "Minimum seconds per measurement")
            ->check(CLI::Range(0.01, 600.0));
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
            // Recorded in each asset's metadata: without the output directory and --json, which
            // do not change the asset, so the same conversion into another directory gives the
            // same bytes (the file name is already a content hash).
            for (int i = 0; i < argc; ++i) {
                // The program by its name only: the same conversion run from another install
                // or build directory gives the same asset.
                const std::string a =
                    i == 0 ? std::filesystem::path(argv[0]).filename().string() : std::string(argv[i]);
                if (a == "-o" || a == "--output") {
                    ++i;
                    continue;
                }
                if (a == "--json" || a.rfind("--output=", 0) == 0 ||
                    (a.size() > 2 && a.rfind("-o", 0) == 0 && a[2] != '-'))
                    continue;
                convert_opts.command_line += (convert_opts.command_line.empty() ? "" : " ") + a;
            }
            return run_convert(convert_opts, convert_json);
        }
        if (*evalc) return run_eval(eval_opts, eval_camera, eval_light, eval_moves, eval_json);
        if (*bench) {
            nlohmann::json report;
            std::string err;
            if (*bench_train)
                report = lsnif::converter::bench_train(bench_opts);
            else if (*bench_infer)
                report = lsnif::converter::bench_infer(bench_opts);
            else if (*bench_memory)
                report = lsnif::converter::bench_memory(scene_bench, err);
            else if (*bench_rays)
                report = lsnif::converter::bench_rays(scene_bench, err);
            else
                report = lsnif::converter::bench_convert(bench_convert_opts, err);
            if (report.is_null()) {
                std::fprintf(stderr, "error: %s\n", err.c_str());
                return 1;
            }
            std::cout << (bench_json ? report.dump(2) + "\n" : lsnif::converter::bench_text(report));
            return 0;
        }
    } catch (const std::exception& e) {
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
    return 2;
}
