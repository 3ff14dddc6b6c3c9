// Helpers shared by the importers of lsnif::scene (not installed, not public).
#pragma once

#include <lsnif/scene/scene.hpp>

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include <filesystem>

namespace lsnif::scene::detail {

// Collects warnings, at most kMaxWarnings lines; the rest are counted and summarized by
// finish() so that a file with a million skipped faces cannot flood the caller.
class WarningSink {
public:
    static constexpr std::size_t kMaxWarnings = 100;
    void add(std::string line);
    // Moves the collected lines (plus a summary line when some were dropped) into `out`.
    void finish(std::vector<std::string>& out);

private:
    std::vector<std::string> lines_;
    std::size_t dropped_ = 0;
};

// Finalizes mesh.normals. On entry normals.size() == positions.size() and
// has_source_normal[v] != 0 marks vertices whose normal came from the file (any length).
// Those are normalized; the others, and file normals that are zero or not finite, get the
// area-weighted normal of compute_vertex_normals(). Sets mesh.normal_origin.
// `what` names the mesh in the warning about unusable file normals.
void finalize_normals(Mesh& mesh, const std::vector<std::uint8_t>& has_source_normal, std::string_view what,
                      WarningSink& warnings);

// "'name'" quoted for messages, or "" when empty.
std::string quote_name(std::string_view name);

// Lower-case extension including the dot (".gltf"), "" when none.
std::string lower_extension(const std::string& path);

// Checks that `path` is a readable regular file and sets `size` to its byte count.
// Returns "" or the problem, phrased to follow "<file>: ".
std::string regular_file_size(const std::filesystem::path& path, std::uintmax_t& size);

}  // namespace lsnif::scene::detail
