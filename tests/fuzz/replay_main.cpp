// Runs a libFuzzer target over files and directories without libFuzzer (GCC builds,
// CTest): each input once. Exit 0 unless a file cannot be read; crashes are crashes.
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

int main(int argc, char** argv) {
    namespace fs = std::filesystem;
    std::size_t runs = 0;
    auto run = [&](const fs::path& p) -> bool {
        std::ifstream f(p, std::ios::binary);
        if (!f) return false;
        std::vector<std::uint8_t> b((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
        LLVMFuzzerTestOneInput(b.data(), b.size());
        ++runs;
        return true;
    };
    for (int i = 1; i < argc; ++i) {
        const fs::path p = argv[i];
        if (fs::is_directory(p)) {
            for (const auto& e : fs::recursive_directory_iterator(p))
                if (e.is_regular_file() && !run(e.path())) {
                    std::fprintf(stderr, "error: cannot read %s\n", e.path().c_str());
                    return 1;
                }
        } else if (!run(p)) {
            std::fprintf(stderr, "error: cannot read %s\n", p.c_str());
            return 1;
        }
    }
    std::printf("replayed %zu inputs\n", runs);
    return runs ? 0 : 1;
}
