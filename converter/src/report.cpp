// The text report of a conversion (what `lsnif convert` prints).
#include <lsnif/converter/convert.hpp>
#include "convert_stages.hpp"

#include <cinttypes>

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

namespace {

// "812 B", "406.2 KiB", "84.1 MiB", "1.20 GiB": a byte count as the text report shows it.
std::string human_bytes(std::uint64_t bytes) {
    char buf[32];
    if (bytes < 1024)
        std::snprintf(buf, sizeof buf, "%" PRIu64 " B", bytes);
    else if (bytes < (1u << 20))
        std::snprintf(buf, sizeof buf, "%.1f KiB", double(bytes) / 1024);
    else if (bytes < (1u << 30))
        std::snprintf(buf, sizeof buf, "%.1f MiB", double(bytes) / (1u << 20));
    else
        std::snprintf(buf, sizeof buf, "%.2f GiB", double(bytes) / (1u << 30));
    return buf;
}

// "BVH 84.1 MiB -> 406.2 KiB": a mesh's or the scene's memory before and after conversion.
std::string memory_text(const json& memory) {
    const std::uint64_t before = memory["before"].get<std::uint64_t>(),
                        after = memory["after"].get<std::uint64_t>();
    return human_bytes(before) + " -> " + human_bytes(after) +
           (memory.value("estimated", false) ? " (est.)" : "");
}

}  // namespace

std::string convert_text(const ConvertResult& r) {
    std::string s;
    char buf[512];
    if (!r.report.contains("meshes")) return s;
    for (const json& m : r.report["meshes"]) {
        std::snprintf(buf, sizeof buf, "%-8s %-24s %9" PRIu64 " tris  x%-3" PRIu64 "  %-28s",
                      m["class"].get<std::string>().c_str(),
                      m["name"].get<std::string>().substr(0, 24).c_str(), m["triangles"].get<std::uint64_t>(),
                      m.value("instances", std::uint64_t(0)),
                      m.contains("memory") ? memory_text(m["memory"]).c_str() : "");
        s += buf;
        if (m.contains("lsnif")) {
            const json& p = m["metrics"]["families"]["pooled"];
            std::snprintf(
                buf, sizeof buf, "  %s  vis %.2f%%  dist %.3f%%  normal %.1f deg%s",
                m["lsnif"]["file"].get<std::string>().c_str(), 100 * p["visibility_accuracy"].get<double>(),
                p["distance_error_median_pct"].get<double>(), p["normal_error_median_deg"].get<double>(),
                m["lsnif"]["reused"].get<bool>() ? " (reused)" : "");
            s += buf;
            if (m.contains("target") && !m["target"]["met"].get<bool>())
                s +=
                    "\n           target missed, gate passed: " + m["target"]["misses"][0].get<std::string>();
            if (m.contains("stopped_early")) {
                std::snprintf(buf, sizeof buf,
                              "\n           trained %u of %u steps: the validation curve met the target",
                              m["stopped_early"]["step"].get<unsigned>(),
                              m["stopped_early"]["steps"].get<unsigned>());
                s += buf;
            }
            const json& fam = m["metrics"]["families"];
            for (const char* f : {"outside", "surface", "interior"}) {
                std::snprintf(buf, sizeof buf,
                              "\n           %-8s vis %.2f%%  dist %.3f%% (p95 %.2f%%)  normal %.1f deg (p95 "
                              "%.1f)  culled %.0f%%",
                              f, 100 * fam[f]["visibility_accuracy"].get<double>(),
                              fam[f]["distance_error_median_pct"].get<double>(),
                              fam[f]["distance_error_p95_pct"].get<double>(),
                              fam[f]["normal_error_median_deg"].get<double>(),
                              fam[f]["normal_error_p95_deg"].get<double>(),
                              100 * fam[f]["culled_fraction"].get<double>());
                s += buf;
            }
        } else if (!m["reasons"].empty()) {
            s += "  " + m["reasons"].back().get<std::string>();
        }
        s += "\n";
    }
    std::snprintf(buf, sizeof buf, "%zu meshes, %" PRIu64 " instances\n", r.report["meshes"].size(),
                  r.report["instances"].get<std::uint64_t>());
    s += buf;
    if (r.report.contains("scene_memory")) {
        const json& mem = r.report["scene_memory"];
        s += "scene memory (each mesh once): " + memory_text(mem);
        if (mem.contains("budget"))
            s += std::string(", budget ") + human_bytes(mem["budget"].get<std::uint64_t>()) +
                 (mem["fits"].get<bool>() ? ": fits" : ": over budget");
        s += "\n";
    }
    if (r.report.contains("manifest")) s += "manifest: " + r.report["manifest"].get<std::string>() + "\n";
    if (r.report.contains("gltf")) s += "glTF: " + r.report["gltf"].get<std::string>() + "\n";
    if (r.report.value("dry_run", false)) s += "dry run: nothing written\n";
    return s;
}

}  // namespace lsnif::converter
