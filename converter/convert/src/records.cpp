// What a conversion records as JSON besides a mesh's outcome (outcome.cpp): the model's
// description and the manifest document.
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/converter/metadata_names.hpp>
#include <lsnif/converter/settings.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

namespace stages {

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

json manifest_json(const Run& run, const std::vector<InputRecord>& inputs,
                   const std::vector<MeshOutcome>& meshes, const json& instances, const SceneMemory& memory,
                   OutcomeFields fields) {
    json input_docs = json::array(), mesh_docs = json::array();
    for (const InputRecord& in : inputs) input_docs.push_back(input_json(in));
    for (const MeshOutcome& o : meshes) mesh_docs.push_back(outcome_json(o, fields));
    json manifest = {
        {"format", kManifestFormat},
        {"tool",
         {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}, {"identity", tool_identity().digest}}},
        {"settings", settings_json(run.opt)},
        {"inputs", input_docs},
        {"meshes", mesh_docs},
        {"instances", instances},
        {"simple_geometry",
         {{"location", "inputs"},
          {"note", "simple meshes are read from their input file (meshes[].input, meshes[].source_mesh)"}}},
        {"scene_memory", scene_memory_json(memory)}};
    return manifest;
}

}  // namespace stages

}  // namespace lsnif::converter
