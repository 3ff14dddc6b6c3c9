#include <lsnif/converter/manifest.hpp>
#include <lsnif/format/container.hpp>

#include <fstream>

namespace lsnif::converter {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

// Symbolic links in the directories are resolved (the kernel resolves "..", in the path we
// record, physically), but not the file itself: a source that is a link stays that link.
fs::path physical_location(const fs::path& p, bool is_file) {
    std::error_code ec;
    const fs::path abs = fs::absolute(p, ec);
    if (ec) return p;
    const fs::path dir = fs::weakly_canonical(is_file ? abs.parent_path() : abs, ec);
    if (ec) return abs;
    return is_file ? dir / abs.filename() : dir;
}

// The typed inputs and meshes of out.doc; false (and which field is wrong) for an entry that
// is not what this lsnif writes.
bool read_entries(LoadedManifest& out, std::string& error) {
    const json &inputs = out.doc["inputs"], &meshes = out.doc["meshes"];
    out.inputs.clear();
    out.meshes.clear();
    for (std::size_t i = 0; i < inputs.size(); ++i) {
        auto in = input_from_json(inputs[i]);
        if (!in) {
            error = "inputs[" + std::to_string(i) + "]." + in.error();
            return false;
        }
        out.inputs.push_back(std::move(*in));
    }
    for (std::size_t i = 0; i < meshes.size(); ++i) {
        auto m = outcome_from_json(meshes[i]);
        if (!m) {
            error = "meshes[" + std::to_string(i) + "]." + m.error();
            return false;
        }
        if (m->input >= out.inputs.size()) {
            error = "meshes[" + std::to_string(i) + "].input: no input " + std::to_string(m->input);
            return false;
        }
        out.meshes.push_back(std::move(*m));
    }
    return true;
}

}  // namespace

std::string write_manifest(const fs::path& outdir, const nlohmann::json& manifest) {
    std::error_code ec;
    fs::create_directories(outdir, ec);
    if (ec) return outdir.string() + ": cannot create the output directory: " + ec.message();
    const format::Error e =
        format::write_text_atomically((outdir / "manifest.json").string(), manifest.dump(2) + "\n");
    return e ? e.message : std::string();
}

std::string manifest_relative_path(const fs::path& input, const fs::path& manifest_dir) {
    const fs::path file = physical_location(input, true), dir = physical_location(manifest_dir, false);
    const fs::path rel = file.lexically_relative(dir);
    return (rel.empty() ? file : rel).generic_string();
}

bool load_manifest(const fs::path& outdir, const std::vector<std::string>& sources, LoadedManifest& out,
                   std::string& error) {
    out.path = outdir / "manifest.json";
    const std::string where = out.path.string();
    std::ifstream in(out.path, std::ios::binary);
    if (!in) {
        error = where + ": cannot open (is it a `lsnif convert` output directory?)";
        return false;
    }
    out.doc = json::parse(in, nullptr, false);
    if (!out.doc.is_object()) {
        error = where + ": not a manifest (not a JSON object)";
        return false;
    }
    const json format = out.doc.value("format", json());
    if (format != kManifestFormat) {
        error = where + ": manifest format " +
                (format.is_string() ? format.get<std::string>() : format.dump()) + ", this lsnif reads " +
                kManifestFormat +
                " (inputs relative to the manifest): re-run lsnif convert, which reuses the assets";
        return false;
    }
    for (const char* key : {"inputs", "meshes", "instances"})
        if (!out.doc.contains(key) || !out.doc[key].is_array()) {
            error = where + ": not a manifest (" + key + " is not an array)";
            return false;
        }
    const json& inputs = out.doc["inputs"];
    if (!read_entries(out, error)) {
        error = where + ": " + error;
        return false;
    }
    if (!sources.empty()) {
        if (sources.size() != inputs.size()) {
            error = where + ": the conversion had " + std::to_string(inputs.size()) +
                    " inputs, --source gives " + std::to_string(sources.size());
            return false;
        }
        out.sources = sources;
        return true;
    }
    out.sources.clear();
    for (std::size_t i = 0; i < out.inputs.size(); ++i) {
        if (out.inputs[i].path.empty()) {
            error = where + ": input " + std::to_string(i) + " has no path";
            return false;
        }
        // operator/ keeps an absolute right-hand side as it is: the rule's one exception.
        out.sources.push_back((outdir / out.inputs[i].path).string());
    }
    return true;
}

}  // namespace lsnif::converter
