// The identity of the code that converts, for cache keys (docs/pipeline.md "Cache keys").
#include <lsnif/cache/cache.hpp>
#include <lsnif/converter/convert.hpp>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <set>
#include <sstream>
#include <string>
#include <vector>

namespace lsnif::converter {

namespace {

// Paths of the files mapped executable into this process (the executable and its shared
// libraries), from /proc/self/maps.
std::set<std::string> executable_mappings() {
    std::set<std::string> paths;
    std::ifstream maps("/proc/self/maps");
    std::string line;
    while (std::getline(maps, line)) {
        std::istringstream fields(line);
        std::string range, perms, offset, dev, inode, path;
        fields >> range >> perms >> offset >> dev >> inode;
        std::getline(fields >> std::ws, path);
        if (perms.size() >= 3 && perms[2] == 'x' && !path.empty() && path[0] == '/') paths.insert(path);
    }
    return paths;
}

std::string file_digest(const std::string& path) {
    std::ifstream f(path, std::ios::binary);
    if (!f) return "unreadable:" + path;
    cache::Sha256 h;
    std::vector<char> buf(1 << 20);
    while (f.read(buf.data(), std::streamsize(buf.size())) || f.gcount() > 0)
        h.update({reinterpret_cast<const std::uint8_t*>(buf.data()), std::size_t(f.gcount())});
    return h.hex();
}

std::string compute_build_identity() {
    // Digests, not paths, sorted: two machines with the same binary and the same Debian
    // packages agree wherever the files live.
    std::vector<std::string> digests;
    for (const std::string& path : executable_mappings()) digests.push_back(file_digest(path));
    std::sort(digests.begin(), digests.end());
    cache::Sha256 h;
    h.update("lsnif-build/1\n").update(LSNIF_VERSION_STRING).update("\n");
    for (const std::string& d : digests) h.update(d).update("\n");
    return h.hex();
}

}  // namespace

const std::string& build_identity() {
    static const std::string id = compute_build_identity();
    return id;
}

std::string executable_path() {
    std::error_code ec;
    const std::filesystem::path p = std::filesystem::read_symlink("/proc/self/exe", ec);
    return ec ? std::string() : p.string();
}

}  // namespace lsnif::converter
