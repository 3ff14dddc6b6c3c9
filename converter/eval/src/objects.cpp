// `lsnif eval --objects`: every converted object alone in its held-out views, through its
// shipped asset (eval.hpp, render_objects).
#include <lsnif/base/text.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/eval/eval.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/scene/scene.hpp>

#include <filesystem>
#include <optional>

namespace lsnif::eval {

using converter::LoadedManifest;
using converter::MeshOutcome;
using render::ObjectViewOptions;
using render::ObjectViews;

namespace {

// One converted object's views into `dir`: its report entry, or an error.
base::Result<ObjectImages, std::string> object_entry(const scene::Mesh& mesh, const MeshOutcome& mo,
                                                     const std::filesystem::path& asset,
                                                     const ObjectViewOptions& o,
                                                     const std::filesystem::path& dir) {
    auto bytes = format::read_file_bytes(asset.string());
    if (!bytes) return bytes.error().message;
    std::string error;
    auto views = ObjectViews::create(mesh.positions, mesh.indices, mesh.normals, o, error);
    if (!views) return mesh.name + ": " + error;
    auto flip = views->compare(*bytes, dir.string());
    if (!flip) return asset.string() + ": " + flip.error();
    ObjectImages entry{mo.name, mo.id, mo.asset->file, *flip, {}};
    for (std::uint32_t k = 0; k < views->view_count(); ++k) {
        const std::string stem = (dir.filename() / ("view" + std::to_string(k) + "_")).string();
        entry.views.push_back({stem + "reference.png", stem + "hybrid.png", stem + "flip.png"});
    }
    return entry;
}

// The source mesh of `mo`, imported once per input into `scenes`; an error when it cannot be
// read or is no longer the converted geometry.
base::Result<const scene::Mesh*, std::string> source_mesh(const LoadedManifest& loaded, const MeshOutcome& mo,
                                                          std::vector<std::optional<scene::Scene>>& scenes) {
    if (!scenes[mo.input]) {
        auto imported = scene::import_scene(loaded.sources[mo.input]);
        if (!imported.ok())
            return loaded.path.string() + ": input " + std::to_string(mo.input) + ": " + imported.error;
        scenes[mo.input] = std::move(imported.scene);
    }
    const auto& meshes = scenes[mo.input]->meshes;
    if (mo.source_mesh >= meshes.size() || scene::geometry_hash(meshes[mo.source_mesh]) != mo.geometry_hash)
        return loaded.sources[mo.input] + ": mesh '" + mo.name +
               "' differs from the converted geometry (geometry hash mismatch): re-run lsnif convert";
    return &meshes[mo.source_mesh];
}

}  // namespace

ObjectsResult render_objects(const EvalOptions& opt) {
    ObjectsResult res;
    LoadedManifest loaded;
    std::string error;
    if (!converter::load_manifest(opt.outdir, opt.sources, loaded, error)) {
        res.errors.push_back(error);
        return res;
    }
    const std::filesystem::path images = (opt.images_dir.empty() ? std::filesystem::path(opt.outdir) / "eval"
                                                                 : std::filesystem::path(opt.images_dir)) /
                                         "objects";
    // The held-out views of the conversion: the ones its manifest reports.
    ObjectViewOptions o;
    o.threads = opt.threads;
    const nlohmann::json& settings = loaded.doc["settings"];
    o.seed =
        converter::held_out_view_seed(settings.value("view_seed", settings.value("seed", std::uint64_t(1))));
    ObjectsReport report;
    std::vector<std::optional<scene::Scene>> scenes(loaded.sources.size());
    for (const MeshOutcome& mo : loaded.meshes) {
        if (!mo.asset) continue;
        auto mesh = source_mesh(loaded, mo, scenes);
        if (!mesh) {
            res.errors.push_back(mesh.error());
            return res;
        }
        const std::string stem = std::filesystem::path(mo.asset->file).stem().string();
        auto entry =
            object_entry(**mesh, mo, std::filesystem::path(opt.outdir) / mo.asset->file, o, images / stem);
        if (!entry) {
            res.errors.push_back(entry.error());
            return res;
        }
        report.objects.push_back(std::move(*entry));
    }
    report.images_dir = images.string();
    report.views = o.views;
    report.width = o.width;
    report.height = o.height;
    report.ao_samples = o.ao_samples;
    res.report = std::move(report);
    return res;
}

nlohmann::json objects_report_json(const ObjectsReport& r) {
    nlohmann::json objects = nlohmann::json::array();
    for (const ObjectImages& o : r.objects) {
        nlohmann::json views = nlohmann::json::array();
        for (const auto& v : o.views)
            views.push_back({{"reference", v[0]}, {"hybrid", v[1]}, {"flip", v[2]}});
        objects.push_back({{"name", o.name},
                           {"mesh", o.mesh},
                           {"lsnif", o.asset},
                           {"flip", converter::object_flip_json(o.flip)},
                           {"views", views}});
    }
    return {{"objects", objects}, {"images_dir", r.images_dir}, {"views", r.views},
            {"width", r.width},   {"height", r.height},         {"ao_samples", r.ao_samples}};
}

std::string objects_report_text(const ObjectsReport& r) {
    std::string out;
    for (const ObjectImages& o : r.objects)
        out +=
            base::printed("%-24s FLIP over its pixels %.4f (p95 %.4f), over the frame %.4f\n", o.name.c_str(),
                          o.flip.combined_object, o.flip.combined_object_p95, o.flip.combined);
    out += "images in " + r.images_dir + "\n";
    return out;
}

}  // namespace lsnif::eval
