// What a conversion records, as JSON: metrics, the model, the target, the manifest. The one
// place these documents are written (and the metrics read back, for reuse).
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/converter/settings.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

json metrics_json(const samples::Metrics& m) {
    return {{"outside", family_json(m.family[0])},
            {"surface", family_json(m.family[1])},
            {"interior", family_json(m.family[2])},
            {"pooled", family_json(m.pooled)}};
}

namespace stages {

json vec3(const std::array<float, 3>& v) {
    return json::array({v[0], v[1], v[2]});
}

json family_json(const samples::FamilyMetrics& f) {
    return {{"rays", f.rays},
            {"visibility_accuracy", f.visibility_accuracy},
            {"false_hit_rate", f.false_hit_rate},
            {"false_miss_rate", f.false_miss_rate},
            {"distance_error_median_pct", f.distance_median_pct},
            {"distance_error_p95_pct", f.distance_p95_pct},
            {"normal_error_median_deg", f.normal_median_deg},
            {"normal_error_p95_deg", f.normal_p95_deg},
            {"geometric_normal_error_median_deg", f.geometric_normal_median_deg},
            {"culled_fraction", f.culled_fraction}};
}

// family_json read back (asset metadata of an earlier run): every field present and of its
// type, or nothing. No field defaults: a decision never reads a value nobody measured.
std::optional<samples::FamilyMetrics> family_from_json(const json& j) {
    if (!j.is_object()) return std::nullopt;
    samples::FamilyMetrics f;
    const std::pair<const char*, double*> numbers[] = {
        {"visibility_accuracy", &f.visibility_accuracy},
        {"false_hit_rate", &f.false_hit_rate},
        {"false_miss_rate", &f.false_miss_rate},
        {"distance_error_median_pct", &f.distance_median_pct},
        {"distance_error_p95_pct", &f.distance_p95_pct},
        {"normal_error_median_deg", &f.normal_median_deg},
        {"normal_error_p95_deg", &f.normal_p95_deg},
        {"geometric_normal_error_median_deg", &f.geometric_normal_median_deg},
        {"culled_fraction", &f.culled_fraction}};
    for (const auto& [key, field] : numbers) {
        if (!j.contains(key) || !j[key].is_number()) return std::nullopt;
        *field = j[key].get<double>();
    }
    if (!j.contains("rays") || !j["rays"].is_number_unsigned()) return std::nullopt;
    f.rays = j["rays"].get<std::uint64_t>();
    return f;
}

json model_json(const format::ModelDesc& d) {
    return {{"grid_resolution", d.grid_resolution},
            {"max_points", d.max_points},
            {"level_resolutions", d.level_resolution},
            {"features_per_level", d.features_per_level},
            {"log2_table_size", d.log2_table_size},
            {"hidden_widths", d.hidden_width},
            {"output_count", d.output_count()},
            {"material_count", d.material_count},
            {"activation", "relu"},
            {"distance_encoding", distance_encoding_name(d.distance_encoding)},
            {"grid_encoding", grid_encoding_name(std::uint32_t(d.grid_encoding))},
            {"ray_inputs", ray_inputs_name(d.ray_inputs)},
            {"normal", "shading"},
            {"parameter_count", d.parameter_count()}};
}

// The target as the manifest's settings record it.
json target_settings(const Target& t) {
    return {{"visibility", t.visibility}, {"distance_pct", t.distance_pct}, {"normal_deg", t.normal_deg}};
}

json target_json(const Target& t, const std::vector<std::string>& misses) {
    json j = target_settings(t);
    j["met"] = misses.empty();
    if (!misses.empty()) j["misses"] = misses;
    return j;
}

json manifest_json(const Run& run, const json& inputs, const json& meshes, const json& instances,
                   const json& memory) {
    json manifest = {
        {"format", kManifestFormat},
        {"tool",
         {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}, {"identity", tool_identity().digest}}},
        {"settings", settings_json(run.opt)},
        {"inputs", inputs},
        {"meshes", meshes},
        {"instances", instances},
        {"simple_geometry",
         {{"location", "inputs"},
          {"note", "simple meshes are read from their input file (meshes[].input, meshes[].source_mesh)"}}},
        {"scene_memory", memory}};
    return manifest;
}

}  // namespace stages

}  // namespace lsnif::converter
