// The settings table (lsnif/converter/settings.hpp).
#include <lsnif/converter/settings.hpp>

#include <cctype>
#include <charconv>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstring>

namespace lsnif::converter {

using nlohmann::json;

namespace {

// A whole number in [lo, hi], written in decimal.
template <class T>
bool parse_count(const std::string& text, T lo, T hi, T& out, std::string& error) {
    T v{};
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (text.empty() || ec != std::errc() || end != text.data() + text.size() || v < lo || v > hi) {
        error = "expected a whole number from " + std::to_string(lo) + " to " + std::to_string(hi);
        return false;
    }
    out = v;
    return true;
}

// A number in [0, 1] (a FLIP value).
bool parse_fraction(const std::string& text, double& out, std::string& error) {
    double x = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), x);
    if (text.empty() || ec != std::errc() || end != text.data() + text.size() || !(x >= 0 && x <= 1)) {
        error = "expected a number from 0 to 1";
        return false;
    }
    out = x;
    return true;
}

// "%.17g": a double that reads back as the same double.
std::string exact(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.17g", v);
    return buf;
}

std::vector<std::string> unless_zero(std::uint64_t v) {
    return v ? std::vector<std::string>{std::to_string(v)} : std::vector<std::string>{};
}

json json_unless_zero(std::uint64_t v) {
    return v ? json(v) : json();
}

// A model or training override: 0 = the preset's value.
#define LSNIF_OVERRIDE(NAME, VALUE, KEY, FIELD, LO, HI, HELP)                           \
    Setting {                                                                           \
        NAME, VALUE, false, SettingScope::mesh, KEY, "the preset's", HELP,              \
            [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) { \
                return parse_count<std::uint32_t>(v, LO, HI, o.FIELD, e);               \
            },                                                                          \
            [](const ConvertOptions& o) { return unless_zero(o.FIELD); },               \
            [](const ConvertOptions& o) { return json_unless_zero(o.FIELD); }           \
    }

// A flag that is off by default.
#define LSNIF_FLAG(NAME, KEY, FIELD, SCOPE, HELP)                                           \
    Setting {                                                                               \
        NAME, nullptr, false, SCOPE, KEY, "off", HELP,                                      \
            [](ConvertOptions& o, const std::string&, std::string&, std::string&) {         \
                return o.FIELD = true;                                                      \
            },                                                                              \
            [](const ConvertOptions& o) {                                                   \
                return o.FIELD ? std::vector<std::string>{""} : std::vector<std::string>{}; \
            },                                                                              \
            [](const ConvertOptions& o) { return o.FIELD ? json(true) : json(); }           \
    }

// One row per setting, in --help's order: a table, as long as the settings are many.
std::vector<Setting> make_table() {
    return {
        Setting{"--preset", "NAME", false, SettingScope::mesh, "preset", "default",
                "default, fast, quality or smoke (pipeline check)",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    Preset p;
                    if (find_preset(v, p)) return o.preset = v, true;
                    e = "not a preset (default, fast, quality, smoke)";
                    return false;
                },
                [](const ConvertOptions& o) { return std::vector<std::string>{o.preset}; },
                [](const ConvertOptions& o) { return json(o.preset); }},
        Setting{"--seed", "N", false, SettingScope::mesh, "seed", "1", "Random seed (sampling and training)",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    return parse_count<std::uint64_t>(v, 0, UINT64_MAX, o.seed, e);
                },
                [](const ConvertOptions& o) { return std::vector<std::string>{std::to_string(o.seed)}; },
                [](const ConvertOptions& o) { return json(o.seed); }},
        Setting{"--arithmetic", "canonical|machine", false, SettingScope::mesh, "arithmetic", "canonical",
                "canonical: fp32 in one order, the same assets on every CPU and thread count; machine: bf16 "
                "training products on AMX or AVX-512 BF16 where present (faster there; the assets depend on "
                "the CPU kind and say so)",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    if (parse_arithmetic(v, o.arithmetic)) return true;
                    e = "expected canonical or machine";
                    return false;
                },
                // As it runs here: machine on a CPU without bf16 products is the canonical arithmetic.
                [](const ConvertOptions& o) {
                    return arithmetic_id(o.arithmetic) != arithmetic_id(Arithmetic::canonical)
                               ? std::vector<std::string>{"machine"}
                               : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) { return json(arithmetic_id(o.arithmetic)); }},
        Setting{"--complex", "NAME", true, SettingScope::scene, "forced_complex", "none",
                "Force a mesh (by name) to become an LSNIF; once per mesh",
                [](ConvertOptions& o, const std::string& v, std::string&, std::string&) {
                    o.force_complex.push_back(v);
                    return true;
                },
                [](const ConvertOptions& o) { return o.force_complex; },
                [](const ConvertOptions& o) { return json(o.force_complex); }},
        Setting{"--simple", "NAME", true, SettingScope::scene, "forced_simple", "none",
                "Force a mesh (by name) to stay BVH; once per mesh",
                [](ConvertOptions& o, const std::string& v, std::string&, std::string&) {
                    o.force_simple.push_back(v);
                    return true;
                },
                [](const ConvertOptions& o) { return o.force_simple; },
                [](const ConvertOptions& o) { return json(o.force_simple); }},
        Setting{"--gate-visibility", "PERCENT", false, SettingScope::mesh, "gate_visibility", "the preset's",
                "Override the pooled held-out visibility an asset needs to ship, in percent (as --target's)",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string& warning) {
                    double x = 0;
                    const auto [end, ec] = std::from_chars(v.data(), v.data() + v.size(), x);
                    if (v.empty() || ec != std::errc() || end != v.data() + v.size() ||
                        !(x >= 0 && x <= 100)) {
                        e = "expected a percentage from 0 to 100";
                        return false;
                    }
                    // It took a fraction before: a value in (0, 1] cannot be meant as a percentage
                    // (no asset is worth shipping at 1 % visibility), so it is read as one.
                    if (x > 0 && x <= 1) {
                        warning = "--gate-visibility takes a percentage now: " + v + " read as " +
                                  exact(100 * x) + " %";
                        x *= 100;
                    }
                    o.gate_min_visibility = x / 100;
                    return true;
                },
                [](const ConvertOptions& o) {
                    return o.gate_min_visibility >= 0
                               ? std::vector<std::string>{exact(100 * o.gate_min_visibility)}
                               : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) {
                    return o.gate_min_visibility >= 0 ? json(o.gate_min_visibility) : json();
                }},
        LSNIF_OVERRIDE("--steps", "N", "steps", steps, 1u, 1000000u, "Override the preset's training steps"),
        LSNIF_OVERRIDE("--batch", "RAYS", "batch", batch_size, 64u, 1u << 20,
                       "Override the preset's batch size (rays per step)"),
        LSNIF_OVERRIDE("--log2-table", "N", "log2_table", log2_table_size, 10u, 24u,
                       "Override T = 2^N hash-table rows per level: the largest table sizing may choose"),
        LSNIF_OVERRIDE("--first-log2-table", "N", "first_log2_table", first_log2_table_size, 10u, 24u,
                       "The table size, 2^N rows, the sizing search starts at before it goes down or up "
                       "(the default preset's 16; at least --log2-table: the largest first)"),
        LSNIF_OVERRIDE("--max-points", "H", "max_points", max_points, 1u, 64u,
                       "Override H, voxel entry points per ray"),
        LSNIF_OVERRIDE("--grid", "V", "grid", grid_resolution, 4u, 256u,
                       "Override V, occupancy grid resolution"),
        LSNIF_OVERRIDE("--hidden", "WIDTH", "hidden", hidden_width, 16u, 512u,
                       "Override the hidden layers' width"),
        LSNIF_OVERRIDE("--max-grid", "V", "max_grid", max_grid_resolution, 4u, 256u,
                       "Override the finest grid a thin object may be trained again at (the grid rung; "
                       "--max-grid equal to --grid: never)"),
        LSNIF_FLAG("--no-ray-inputs", "no_ray_inputs", no_ray_inputs, SettingScope::mesh,
                   "The network sees its points' features only, not the ray's direction and entry offsets "
                   "(container 1.0/1.1 files, for comparisons)"),
        Setting{"--target", "VIS,DIST,NORMAL", false, SettingScope::mesh, "target", "98.5,0.6,8",
                "Accuracy asked of every asset: held-out visibility %, median distance error % of the "
                "diagonal, median normal error in degrees",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    return parse_target(v, o.target, e);
                },
                [](const ConvertOptions& o) {
                    return std::vector<std::string>{exact(100 * o.target.visibility) + "," +
                                                    exact(o.target.distance_pct) + "," +
                                                    exact(o.target.normal_deg)};
                },
                [](const ConvertOptions& o) {
                    return json{{"visibility", o.target.visibility},
                                {"distance_pct", o.target.distance_pct},
                                {"normal_deg", o.target.normal_deg}};
                }},
        Setting{
            "--target-flip", "FLIP", false, SettingScope::mesh, "target_flip", "1 (nothing)",
            "The target's visual term: image error (FLIP of the combined renders over the object's own "
            "pixels, docs/model.md \"Judged by how it looks\") at most this; 1 asks nothing of the images",
            [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                return parse_fraction(v, o.target.flip, e);
            },
            [](const ConvertOptions& o) { return std::vector<std::string>{exact(o.target.flip)}; },
            [](const ConvertOptions& o) { return json(o.target.flip); }},
        Setting{"--view-seed", "N", false, SettingScope::report, "view_seed", "the --seed",
                "Seed of the held-out views a shipped asset's image error is reported on; decisions never "
                "see them, so it changes the report, not the assets",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    std::uint64_t seed = 0;
                    if (!parse_count<std::uint64_t>(v, 0, UINT64_MAX, seed, e)) return false;
                    return o.view_seed = seed, true;
                },
                [](const ConvertOptions& o) {
                    return o.view_seed ? std::vector<std::string>{std::to_string(*o.view_seed)}
                                       : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) { return o.view_seed ? json(*o.view_seed) : json(); }},
        Setting{"--accept", "rays|images|either", false, SettingScope::mesh, "accept", "either",
                "What may ship an asset: its ray metrics passing the gate, its image error within "
                "--gate-flip, or either (docs/model.md \"Judged by how it looks\")",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    Acceptance a{};
                    if (!parse_acceptance(v, a)) return e = "expected rays, images or either", false;
                    return o.accept = a, true;
                },
                [](const ConvertOptions& o) {
                    return o.accept ? std::vector<std::string>{acceptance_name(*o.accept)}
                                    : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) { return o.accept ? json(acceptance_name(*o.accept)) : json(); }},
        Setting{
            "--gate-flip", "FLIP", false, SettingScope::mesh, "gate_flip", "the calibrated gate",
            "Override the image gate: the largest image error (FLIP of the combined renders over the "
            "object's own pixels in its decision views) that ships an asset by the image rule; an asset "
            "shipped above the calibrated gate says so",
            [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                return parse_fraction(v, o.gate_max_flip, e);
            },
            [](const ConvertOptions& o) {
                return o.gate_max_flip >= 0 ? std::vector<std::string>{exact(o.gate_max_flip)}
                                            : std::vector<std::string>{};
            },
            [](const ConvertOptions& o) { return o.gate_max_flip >= 0 ? json(o.gate_max_flip) : json(); }},
        Setting{"--memory-budget", "BYTES", false, SettingScope::scene, "memory_budget", "none",
                "Scene memory to fit, in bytes (K, M, G: powers of 1024): candidates are converted in order "
                "of BVH bytes saved per asset byte until the scene (BVHs + assets, each mesh once) fits; the "
                "rest stay BVH",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    return parse_byte_size(v, o.memory_budget, e);
                },
                [](const ConvertOptions& o) { return unless_zero(o.memory_budget); },
                [](const ConvertOptions& o) { return json_unless_zero(o.memory_budget); }},
        Setting{"--bvh-yardstick", "embree|compressed", false, SettingScope::mesh, "bvh_yardstick", "embree",
                "The BVH an asset's resident bytes are compared with, in the memory rule, the budget and "
                "every memory figure: Embree's as built, or an 8-wide compressed BVH as GPUs hold (80 bytes "
                "per inner node; docs/convert.md \"Memory\")",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    BvhYardstick y{};
                    if (!parse_bvh_yardstick(v, y)) return e = "expected embree or compressed", false;
                    return o.bvh_yardstick = y, true;
                },
                [](const ConvertOptions& o) {
                    return o.bvh_yardstick ? std::vector<std::string>{bvh_yardstick_name(*o.bvh_yardstick)}
                                           : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) {
                    return o.bvh_yardstick ? json(bvh_yardstick_name(*o.bvh_yardstick)) : json();
                }},
        Setting{"--memory-ratio", "X", false, SettingScope::mesh, "memory_ratio", "the preset's (2)",
                "How many times smaller than the yardstick's BVH an asset must be, held in memory, for its "
                "mesh to convert",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    double x = 0;
                    const auto [end, ec] = std::from_chars(v.data(), v.data() + v.size(), x);
                    if (v.empty() || ec != std::errc() || end != v.data() + v.size() ||
                        !(x >= 0.01 && x <= 1e6))
                        return e = "expected a number from 0.01 to 1000000", false;
                    return o.min_memory_ratio = x, true;
                },
                [](const ConvertOptions& o) {
                    return o.min_memory_ratio > 0 ? std::vector<std::string>{exact(o.min_memory_ratio)}
                                                  : std::vector<std::string>{};
                },
                [](const ConvertOptions& o) {
                    return o.min_memory_ratio > 0 ? json(o.min_memory_ratio) : json();
                }},
        LSNIF_FLAG("--fixed-model", "fixed_model", fixed_model, SettingScope::mesh,
                   "Train the preset's model (after the memory rule) for the whole budget: no smaller sizes, "
                   "no 8-bit option, no stop at the target (for sweeps and comparisons)"),
        LSNIF_FLAG("--no-give-up", "no_give_up", no_give_up, SettingScope::mesh,
                   "Train to the end of the budget even when the validation curve shows the gate is out of "
                   "reach (to measure hard geometry); the gate still decides what ships"),
        LSNIF_FLAG("--keep-inactive", "keep_inactive", keep_inactive, SettingScope::mesh,
                   "Ship each trained network whole: do not remove the hidden neurons that no validation ray "
                   "activates (docs/model.md \"Inactive neurons\")"),
        Setting{"--threads", "N", false, SettingScope::run, nullptr, "0: all cores",
                "Worker threads; results are the same for any count",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    return parse_count<std::uint32_t>(v, 0u, 4096u, o.threads, e);
                },
                [](const ConvertOptions& o) { return unless_zero(o.threads); },
                [](const ConvertOptions&) { return json(); }},
        Setting{"-j,--jobs", "JOBS", false, SettingScope::run, nullptr, "1",
                "Meshes converted at once, sharing the threads (each gets threads/jobs); not with "
                "--memory-budget",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    return parse_count<std::uint32_t>(v, 1u, 256u, o.jobs, e);
                },
                [](const ConvertOptions& o) {
                    return o.jobs > 1 ? std::vector<std::string>{std::to_string(o.jobs)}
                                      : std::vector<std::string>{};
                },
                [](const ConvertOptions&) { return json(); }},
        LSNIF_FLAG("--dry-run", nullptr, dry_run, SettingScope::run,
                   "Import and classify only: print the plan (class, reasons, model size, cache key), write "
                   "nothing"),
        Setting{"--cache", "DIR|URL", false, SettingScope::run, nullptr, "none (lsnif batch: required)",
                "Cache of conversion results shared between runs, processes and machines: a directory "
                "(created if absent) or an http(s):// server that stores what is PUT (docs/pipeline.md)",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    if (v.empty()) return e = "expected a directory or an http(s):// URL", false;
                    return o.cache = v, true;
                },
                [](const ConvertOptions&) { return std::vector<std::string>{}; },
                [](const ConvertOptions&) { return json(); }},
        Setting{"--cache-local", "DIR", false, SettingScope::run, nullptr, "none",
                "With a cache server: a directory in front of it, read first and filled from it",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    if (v.empty()) return e = "expected a directory", false;
                    return o.cache_local = v, true;
                },
                [](const ConvertOptions&) { return std::vector<std::string>{}; },
                [](const ConvertOptions&) { return json(); }},
        LSNIF_FLAG("--cache-read-only", nullptr, cache_read_only, SettingScope::run,
                   "Read the cache server, never write to it (e.g. builds of untrusted changes); a "
                   "--cache-local directory is still filled"),
        Setting{"--cache-timeout", "SECONDS", false, SettingScope::run, nullptr, "10",
                "Per request to the cache server, connecting included; a request is tried 3 times (0.25 "
                "and 0.5 s apart), then the server is not asked again in this run",
                [](ConvertOptions& o, const std::string& v, std::string& e, std::string&) {
                    double x = 0;
                    const auto [end, ec] = std::from_chars(v.data(), v.data() + v.size(), x);
                    if (v.empty() || ec != std::errc() || end != v.data() + v.size() || !(x > 0 && x <= 3600))
                        return e = "expected seconds in (0, 3600]", false;
                    return o.cache_timeout = x, true;
                },
                [](const ConvertOptions&) { return std::vector<std::string>{}; },
                [](const ConvertOptions&) { return json(); }},
    };
}

#undef LSNIF_OVERRIDE
#undef LSNIF_FLAG

const Setting* find_setting(const std::string& name) {
    for (const Setting& s : settings_table())
        if (long_name(s) == name) return &s;
    return nullptr;
}

}  // namespace

bool parse_target(const std::string& text, Target& target, std::string& error) {
    double v[3];
    std::size_t pos = 0;
    for (int i = 0; i < 3; ++i) {
        const std::size_t end = text.find(',', pos);
        if ((end == std::string::npos) != (i == 2)) {
            error = "expected VIS,DIST,NORMAL (three numbers, e.g. 97,1.0,15)";
            return false;
        }
        const std::string part = text.substr(pos, end == std::string::npos ? std::string::npos : end - pos);
        char* stop = nullptr;
        v[i] = std::strtod(part.c_str(), &stop);
        if (part.empty() || *stop != '\0' || !std::isfinite(v[i])) {
            error = "'" + part + "' is not a number (expected VIS,DIST,NORMAL, e.g. 97,1.0,15)";
            return false;
        }
        pos = end + 1;
    }
    char why[160] = "";
    if (!(v[0] > 0 && v[0] <= 100))
        std::snprintf(why, sizeof why, "visibility %g %% is outside (0, 100]", v[0]);
    else if (!(v[1] > 0 && v[1] <= 100))
        std::snprintf(why, sizeof why, "distance error %g %% of the diagonal is outside (0, 100]", v[1]);
    else if (!(v[2] > 0 && v[2] <= 180))
        std::snprintf(why, sizeof why, "normal error %g degrees is outside (0, 180]", v[2]);
    if (why[0]) {
        error = why;
        return false;
    }
    target = {v[0] / 100.0, v[1], v[2]};
    return true;
}

bool parse_byte_size(const std::string& text, std::uint64_t& bytes, std::string& error) {
    std::size_t digits = 0;
    while (digits < text.size() &&
           (std::isdigit(static_cast<unsigned char>(text[digits])) || text[digits] == '.'))
        ++digits;
    double value = 0;
    const std::string number = text.substr(0, digits);
    const auto [end, ec] = std::from_chars(number.data(), number.data() + number.size(), value);
    if (number.empty() || ec != std::errc() || end != number.data() + number.size()) {
        error = "expected a byte count such as 1500000, 512K, 64MiB or 1.5G";
        return false;
    }
    std::string unit;
    for (char ch : text.substr(digits)) unit += char(std::tolower(static_cast<unsigned char>(ch)));
    double scale = 1;
    const std::string prefixes = "kmgt";  // 1024^1 .. 1024^4
    if (const std::size_t k = unit.empty() ? std::string::npos : prefixes.find(unit[0]);
        k != std::string::npos) {
        scale = std::ldexp(1.0, 10 * int(k + 1));
        unit.erase(0, 1);
        if (unit == "ib") unit = "b";
    }
    if (!unit.empty() && unit != "b") {
        error = "unknown unit '" + text.substr(digits) + "' (use K, M, G or T: powers of 1024)";
        return false;
    }
    const double total = std::floor(value * scale);
    if (!(total >= 1)) {
        error = "must be at least 1 byte";
        return false;
    }
    if (total > 9.2e18) {
        error = "more than 2^63 bytes";
        return false;
    }
    bytes = std::uint64_t(total);
    return true;
}

const std::vector<Setting>& settings_table() {
    static const std::vector<Setting> table = make_table();
    return table;
}

std::string long_name(const Setting& s) {
    const std::string names = s.names;
    const std::size_t comma = names.rfind(',');
    return comma == std::string::npos ? names : names.substr(comma + 1);
}

std::vector<std::string> settings_arguments(const ConvertOptions& opt) {
    std::vector<std::string> args;
    for (const Setting& s : settings_table()) {
        if (s.scope == SettingScope::run) continue;
        for (const std::string& v : s.get(opt)) {
            args.push_back(long_name(s));
            if (s.value) args.push_back(v);
        }
    }
    return args;
}

bool apply_settings_arguments(const std::vector<std::string>& args, ConvertOptions& opt, std::string& error) {
    for (std::size_t i = 0; i < args.size(); ++i) {
        const Setting* s = find_setting(args[i]);
        if (!s) {
            error = "'" + args[i] + "' is not a setting";
            return false;
        }
        std::string value;
        if (s->value) {
            if (i + 1 == args.size()) {
                error = args[i] + " needs a value";
                return false;
            }
            value = args[++i];
        }
        std::string why, warning;  // a canonical form is never a deprecated one
        if (!s->set(opt, value, why, warning)) {
            error = args[s->value ? i - 1 : i] + " '" + value + "': " + why;
            return false;
        }
    }
    return true;
}

namespace {

std::string scope_key(const ConvertOptions& opt, SettingScope scope) {
    std::string key;
    for (const Setting& s : settings_table()) {
        if (s.scope != scope) continue;
        for (const std::string& v : s.get(opt)) {
            if (!key.empty()) key.append(" ");
            key.append(long_name(s));
            if (s.value) key.append(" ").append(v);
        }
    }
    return key;
}

}  // namespace

std::string mesh_settings_key(const ConvertOptions& opt) {
    return scope_key(opt, SettingScope::mesh);
}

std::string report_settings_key(const ConvertOptions& opt) {
    return scope_key(opt, SettingScope::report);
}

json settings_json(const ConvertOptions& opt) {
    json j = json::object();
    for (const Setting& s : settings_table()) {
        if (!s.manifest) continue;
        json v = s.to_json(opt);
        if (!v.is_null()) j[s.manifest] = std::move(v);
    }
    return j;
}

}  // namespace lsnif::converter
