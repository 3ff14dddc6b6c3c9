// Voxelizer throughput: a real mesh refined by 1-to-4 midpoint subdivision, voxelized
// repeatedly with 1 and 2 threads (and hardware_concurrency() if larger) by default.
//
//   bench_voxelize [mesh.off] [levels=3] [V=32] [repeats=15] [threads=1,2]
//
// Prints a table and, last, one JSON object. Timing covers exactly one voxelize() call
// (validation of the input included); the best and the median of the repeats are given.
#include <lsnif/voxelize/voxelize.hpp>

#include "off_mesh.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

namespace vx = lsnif::voxelize;

int main(int argc, char** argv) {
    const std::string path = argc > 1 ? argv[1] : LSNIF_VOXELIZE_DEFAULT_MESH;
    const int levels = argc > 2 ? std::atoi(argv[2]) : 3;
    const std::uint32_t v = argc > 3 ? std::uint32_t(std::atoi(argv[3])) : 32;
    const int repeats = argc > 4 ? std::max(1, std::atoi(argv[4])) : 15;

    std::string err;
    auto mesh = vx::testing::read_off(path, err);
    if (!mesh) {
        std::fprintf(stderr, "bench_voxelize: %s\n", err.c_str());
        return 1;
    }
    for (int i = 0; i < levels; ++i) *mesh = vx::testing::subdivide(*mesh);
    const vx::MeshView view{mesh->positions, mesh->indices};
    const auto box = vx::padded_box(view);
    if (!box) {
        std::fprintf(stderr, "bench_voxelize: %s\n", box.error().message.c_str());
        return 1;
    }

    std::vector<unsigned> thread_counts;
    if (argc > 5) {
        for (const char* p = argv[5]; *p;) {
            char* end = nullptr;
            const unsigned long n = std::strtoul(p, &end, 10);
            if (end == p || n == 0 || n > 256) {
                std::fprintf(stderr, "bench_voxelize: bad thread list '%s'\n", argv[5]);
                return 1;
            }
            thread_counts.push_back(unsigned(n));
            p = *end == ',' ? end + 1 : end;
        }
    } else {
        thread_counts = {1, 2};
        if (std::thread::hardware_concurrency() > 2)
            thread_counts.push_back(std::thread::hardware_concurrency());
    }

    struct Row {
        unsigned threads;
        double best, median;
        std::size_t occupied;
    };
    std::vector<Row> rows;
    std::vector<std::uint8_t> reference;
    bool identical = true;
    for (unsigned threads : thread_counts) {
        std::vector<double> seconds;
        std::size_t occupied = 0;
        for (int r = 0; r < repeats + 1; ++r) {  // the first run warms caches and is dropped
            const auto t0 = std::chrono::steady_clock::now();
            const auto occ = vx::voxelize(view, *box, v, {threads});
            const auto t1 = std::chrono::steady_clock::now();
            if (!occ) {
                std::fprintf(stderr, "bench_voxelize: %s\n", occ.error().message.c_str());
                return 1;
            }
            if (reference.empty()) reference = occ->bits;
            identical = identical && occ->bits == reference;
            occupied = occ->count();
            if (r > 0) seconds.push_back(std::chrono::duration<double>(t1 - t0).count());
        }
        std::sort(seconds.begin(), seconds.end());
        rows.push_back({threads, seconds.front(), seconds[seconds.size() / 2], occupied});
    }

    const double tris = double(mesh->triangle_count());
    std::printf("mesh %s, %d subdivision level(s): %zu triangles, %zu vertices; V = %u; %d timed runs each\n",
                path.c_str(), levels, mesh->triangle_count(), mesh->vertex_count(), v, repeats);
    std::printf("%8s %12s %12s %16s %16s %10s\n", "threads", "best ms", "median ms", "best Mtri/s",
                "median Mtri/s", "occupied");
    for (const Row& r : rows)
        std::printf("%8u %12.3f %12.3f %16.1f %16.1f %10zu\n", r.threads, r.best * 1e3, r.median * 1e3,
                    tris / r.best * 1e-6, tris / r.median * 1e-6, r.occupied);
    std::printf(
        "{\"mesh\": \"%s\", \"levels\": %d, \"triangles\": %zu, \"resolution\": %u, \"repeats\": %d, "
        "\"identical_across_threads\": %s, \"runs\": [",
        path.c_str(), levels, mesh->triangle_count(), v, repeats, identical ? "true" : "false");
    for (std::size_t i = 0; i < rows.size(); ++i)
        std::printf(
            "%s{\"threads\": %u, \"best_s\": %.6f, \"median_s\": %.6f, \"best_triangles_per_s\": %.0f, "
            "\"median_triangles_per_s\": %.0f}",
            i ? ", " : "", rows[i].threads, rows[i].best, rows[i].median, tris / rows[i].best,
            tris / rows[i].median);
    std::printf("]}\n");
    return identical ? 0 : 1;
}
