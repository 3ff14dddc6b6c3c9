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

// "a; b; c".
std::string join(const std::vector<std::string>& parts) {
    std::string s;
    for (const std::string& p : parts) s += (s.empty() ? "" : "; ") + p;
    return s;
}

// before / after, 0 for nothing after.
double ratio(std::uint64_t before, std::uint64_t after) {
    return after ? double(before) / double(after) : 0.0;
}

// "84.1 MiB -> 406.2 KiB": a mesh's or the scene's memory before (its BVH) and after
// conversion (the asset's resident bytes).
std::string memory_text(std::uint64_t before, std::uint64_t after, bool estimated) {
    return human_bytes(before) + " -> " + human_bytes(after) + (estimated ? " (est.)" : "");
}

// The lines of a shipped mesh after its summary: target, early stop, each family's metrics.
std::string shipped_text(const MeshOutcome& m) {
    std::string s;
    char buf[512];
    const samples::FamilyMetrics& p = m.held_out->metrics.pooled;
    std::snprintf(buf, sizeof buf, "  %s  vis %.2f%%  dist %.3f%%  normal %.1f deg%s", m.asset->file.c_str(),
                  100 * p.visibility_accuracy, p.distance_median_pct, p.normal_median_deg,
                  m.asset->reused.value_or(false) ? " (reused)" : "");
    s += buf;
    s += "\n           held in memory " + human_bytes(m.asset->resident_bytes) + ", file " +
         human_bytes(m.asset->bytes);
    if (m.stats) {
        std::snprintf(buf, sizeof buf, "; BVH: Embree %s (%.1fx), compressed %s (%.1fx)",
                      human_bytes(m.stats->bvh.embree).c_str(),
                      ratio(m.stats->bvh.embree, m.asset->resident_bytes),
                      human_bytes(m.stats->bvh.compressed).c_str(),
                      ratio(m.stats->bvh.compressed, m.asset->resident_bytes));
        s += buf;
    }
    if (m.held_out_images) {
        std::snprintf(buf, sizeof buf,
                      "\n           image error on held-out views: FLIP %.4f over its pixels (p95 %.3f)",
                      m.held_out_images->combined_object, m.held_out_images->combined_object_p95);
        s += buf;
    }
    if (const std::uint32_t n = m.held_out->escape_points; n != 0)
        s += "\n           escape rule " + std::to_string(n) + ": rays leaving its surface within " +
             std::to_string(n) + " occupied voxels skip the network";
    const GateVerdict& gate = m.held_out->gate;
    if (gate.by == GatePass::images) {
        s += "\n           shipped by its images";
        if (gate.above_calibrated) s += ", above the calibrated image gate";
        if (!gate.rays_failed.empty()) s += "; rays fail the gate: " + join(gate.rays_failed);
    }
    if (m.target && !m.target->misses.empty())
        s += "\n           target missed, gate passed: " + join(m.target->misses);
    if (m.stopped_early) {
        std::snprintf(buf, sizeof buf,
                      "\n           trained %u of %u steps: the validation curve met the target",
                      m.stopped_early->step, m.stopped_early->steps);
        s += buf;
    }
    for (int f = 0; f < samples::kFamilyCount; ++f) {
        const samples::FamilyMetrics& x = m.held_out->metrics.family[f];
        std::snprintf(buf, sizeof buf,
                      "\n           %-8s vis %.2f%%  dist %.3f%% (p95 %.2f%%)  normal %.1f deg (p95 "
                      "%.1f)  culled %.0f%%",
                      samples::family_name(samples::Family(f)), 100 * x.visibility_accuracy,
                      x.distance_median_pct, x.distance_p95_pct, x.normal_median_deg, x.normal_p95_deg,
                      100 * x.culled_fraction);
        s += buf;
    }
    return s;
}

}  // namespace

std::string convert_text(const ConvertResult& r) {
    std::string s;
    char buf[512];
    if (r.inputs.empty()) return s;  // nothing was imported (the options were refused)
    for (const MeshOutcome& m : r.meshes) {
        const std::string memory =
            m.memory ? memory_text(m.memory->before, m.memory->after, m.memory->estimated) : std::string();
        std::snprintf(buf, sizeof buf, "%-8s %-24s %9" PRIu64 " tris  x%-3" PRIu64 "  %-28s",
                      std::string(class_name(m.cls())).c_str(), m.name.substr(0, 24).c_str(), m.triangles,
                      m.instances, memory.c_str());
        s += buf;
        if (m.asset)
            s += shipped_text(m);
        else if (!m.reasons.empty())
            s += "  " + m.reasons.back();
        s += "\n";
    }
    std::snprintf(buf, sizeof buf, "%zu meshes, %zu instances\n", r.meshes.size(), r.instances);
    s += buf;
    if (r.memory) {
        s += std::string("scene memory (each mesh once; ") +
             (r.memory->yardstick == BvhYardstick::compressed ? "compressed" : "Embree") +
             " BVHs, assets as held in memory): " +
             memory_text(r.memory->before, r.memory->after, r.memory->estimated);
        if (r.memory->budget)
            s += ", budget " + human_bytes(*r.memory->budget) +
                 (r.memory->fits() ? ": fits" : ": over budget");
        s += "\n";
    }
    if (!r.manifest_path.empty()) s += "manifest: " + r.manifest_path + "\n";
    if (!r.gltf_path.empty()) s += "glTF: " + r.gltf_path + "\n";
    if (r.dry_run) s += "dry run: nothing written\n";
    return s;
}

}  // namespace lsnif::converter
