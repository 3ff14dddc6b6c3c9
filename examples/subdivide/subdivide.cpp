// lsnif_subdivide: Loop-subdivides a triangle mesh with OpenMesh's uniform Loop subdivider
// (OpenMesh::Subdivider::Uniform::LoopT), so benchmarks can show how conversion cost and
// BVH memory grow with triangle count on a real shape (each iteration multiplies the
// triangle count by 4: CGAL's 20k-triangle dragon becomes 1.3 M triangles after 3).
//
//   lsnif_subdivide IN OUT [--iterations N]     N in [1, 6], default 3
//
// IN and OUT are any format OpenMesh reads/writes (OFF, OBJ, PLY, STL); PLY and STL are
// written binary. Non-triangle faces are triangulated first. The output is written to a
// temporary file in OUT's directory and renamed, so a failed run leaves nothing behind.
#include <OpenMesh/Core/IO/MeshIO.hh>
#include <OpenMesh/Core/Mesh/TriMesh_ArrayKernelT.hh>
#include <OpenMesh/Tools/Subdivider/Uniform/LoopT.hh>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <system_error>

namespace {

using Mesh = OpenMesh::TriMesh_ArrayKernelT<>;

int fail(const std::string& msg) {
    std::fprintf(stderr, "error: %s\n", msg.c_str());
    return 1;
}

}  // namespace

int main(int argc, char** argv) {
    namespace fs = std::filesystem;
    std::string in, out;
    int iterations = 3;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--iterations" && i + 1 < argc) {
            try {
                iterations = std::stoi(argv[++i]);
            } catch (...) {
                return fail("--iterations: not a number: " + std::string(argv[i]));
            }
        } else if (a == "-h" || a == "--help") {
            std::printf("usage: lsnif_subdivide IN OUT [--iterations N]\n");
            return 0;
        } else if (in.empty()) {
            in = a;
        } else if (out.empty()) {
            out = a;
        } else {
            return fail("unexpected argument: " + a);
        }
    }
    if (in.empty() || out.empty()) return fail("usage: lsnif_subdivide IN OUT [--iterations N]");
    if (iterations < 1 || iterations > 6) return fail("--iterations must be in [1, 6]");

    std::error_code ec;
    if (!fs::is_regular_file(in, ec)) return fail(in + ": no such file");
    Mesh mesh;
    if (!OpenMesh::IO::read_mesh(mesh, in)) return fail(in + ": OpenMesh cannot read it");
    if (mesh.n_faces() == 0) return fail(in + ": no faces");
    for (const auto v : mesh.vertices()) {
        const auto p = mesh.point(v);
        if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2]))
            return fail(in + ": non-finite vertex coordinate");
    }
    const std::size_t faces_in = mesh.n_faces();

    OpenMesh::Subdivider::Uniform::LoopT<Mesh> loop;
    if (!loop.attach(mesh)) return fail(in + ": the Loop subdivider cannot attach to this mesh");
    const bool ok = loop(static_cast<std::size_t>(iterations));
    loop.detach();
    if (!ok) return fail(in + ": Loop subdivision failed");

    const fs::path target(out);
    const fs::path tmp = target.parent_path() / (".tmp-" + target.filename().string());
    OpenMesh::IO::Options opt;
    const std::string ext = target.extension().string();
    if (ext == ".ply" || ext == ".stl") opt += OpenMesh::IO::Options::Binary;
    // OpenMesh picks the writer from the extension, so the temporary keeps it.
    const fs::path tmp_ext = tmp.string() + ext;
    if (!OpenMesh::IO::write_mesh(mesh, tmp_ext.string(), opt)) {
        fs::remove(tmp_ext, ec);
        return fail(out + ": cannot write");
    }
    fs::rename(tmp_ext, target, ec);
    if (ec) {
        fs::remove(tmp_ext, ec);
        return fail(out + ": cannot rename the temporary file: " + ec.message());
    }
    std::printf("%s: %zu -> %zu triangles (%d Loop iterations), %zu vertices\n", out.c_str(), faces_in,
                static_cast<std::size_t>(mesh.n_faces()), iterations,
                static_cast<std::size_t>(mesh.n_vertices()));
    return 0;
}
