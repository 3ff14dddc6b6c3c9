// libFuzzer target for scene import: glTF 2.0 (JSON and binary) through tinygltf and our
// accessor/node checks, and OBJ, PLY, OFF and STL through OpenMesh and our OFF reader.
// The first input byte picks the format (so one corpus covers every importer); the rest is
// the file. An import must either fail with an error naming the file, or return a scene
// that satisfies every invariant check_scene() states; anything else aborts (a finding).
// Built with clang by scripts/fuzz; with GCC and replay_main.cpp as a CTest replaying the
// committed corpus (tests/fuzz/corpus/import).
#include <lsnif/scene/scene.hpp>

#include <unistd.h>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>

namespace {

namespace fs = std::filesystem;

const char* const kExtensions[] = {".gltf", ".glb", ".obj", ".ply", ".off", ".stl"};

// One scratch directory per process: mesh readers take a path, and glTF external buffers
// resolve relative to it (it holds nothing else, so a URI reaches no real data there).
const fs::path& scratch() {
    static const fs::path dir = [] {
        fs::path d = fs::temp_directory_path() / ("lsnif-fuzz-import-" + std::to_string(::getpid()));
        fs::create_directories(d);
        return d;
    }();
    return dir;
}

[[noreturn]] void finding(const std::string& what) {
    std::fprintf(stderr, "fuzz_import: %s\n", what.c_str());
    std::abort();
}

void check(const lsnif::scene::ImportResult& r, const std::string& name) {
    if (!r.ok()) {
        if (r.error.rfind(name, 0) != 0) finding("error does not name the file: " + r.error);
        return;
    }
    const std::string broken = lsnif::scene::check_scene(r.scene);
    if (!broken.empty()) finding("imported scene breaks an invariant: " + broken);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size < 1) return 0;
    const unsigned kind = data[0] % 6;
    const std::span<const std::uint8_t> body(data + 1, size - 1);
    const std::string name = std::string("input") + kExtensions[kind];
    if (kind <= 1) {
        check(lsnif::scene::import_gltf_from_memory(body, scratch(), name), name);
        return 0;
    }
    const fs::path path = scratch() / name;
    {
        std::ofstream f(path, std::ios::binary | std::ios::trunc);
        f.write(reinterpret_cast<const char*>(body.data()), std::streamsize(body.size()));
    }
    check(lsnif::scene::import_mesh_file(path), path.string());
    return 0;
}
