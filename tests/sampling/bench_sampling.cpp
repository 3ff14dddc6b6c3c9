// Ground-truth generation throughput: EmbreeSource::generate() (ray construction, parity
// rejection for family (c), Embree tracing, normal interpolation) against a plain
// parallel rtcIntersect1 loop over the same rays, same thread count (measure_throughput);
// the "packet" line traces the same rays with rtcIntersect16, for comparison only.
//
//   bench_sampling [mesh.off] [rays=3000000] [threads=2] [repeats=5] [subdivisions=0]
//
// `subdivisions` refines the mesh by 1-to-4 midpoint subdivision first (same surface,
// 4x the triangles per level), to show how the ratio moves with the cost of a trace.
//
// Prints the mesh, the BVH memory and one line per quantity; best of `repeats` each.
#include <lsnif/sampling/sampling.hpp>

#include "mesh_helpers.hpp"

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>

using namespace lsnif::sampling;

int main(int argc, char** argv) {
    const std::string path = argc > 1 ? argv[1] : LSNIF_SAMPLING_DEFAULT_MESH;
    const std::size_t rays = argc > 2 ? std::size_t(std::strtoull(argv[2], nullptr, 10)) : 3000000;
    const std::uint32_t threads = argc > 3 ? std::uint32_t(std::atoi(argv[3])) : 2;
    const std::uint32_t repeats = argc > 4 ? std::uint32_t(std::atoi(argv[4])) : 5;
    if (rays == 0 || threads == 0 || repeats == 0) {
        std::fprintf(stderr,
                     "usage: bench_sampling [mesh.off] [rays>0] [threads>0] [repeats>0] [subdivisions]\n");
        return 2;
    }
    std::string err;
    auto mesh = testing::read_off(path, err);
    if (!mesh) {
        std::fprintf(stderr, "bench_sampling: %s\n", err.c_str());
        return 1;
    }
    const int subdivisions = argc > 5 ? std::atoi(argv[5]) : 0;
    for (int i = 0; i < subdivisions; ++i) *mesh = testing::subdivide(*mesh);
    SamplingConfig cfg;
    cfg.threads = threads;
    const auto t0 = std::chrono::steady_clock::now();
    auto src = EmbreeSource::create(mesh->view(), testing::padded_box(*mesh), cfg, err);
    const double build = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!src) {
        std::fprintf(stderr, "bench_sampling: %s\n", err.c_str());
        return 1;
    }
    const GenerationStats st = measure_throughput(*src, 1, rays, repeats);
    double load1 = -1;  // other processes competing for the cores during the run
    if (std::FILE* f = std::fopen("/proc/loadavg", "r")) {
        if (std::fscanf(f, "%lf", &load1) != 1) load1 = -1;
        std::fclose(f);
    }
    const GenerateCounters& c = src->counters();
    std::printf("mesh                 %s (%zu vertices, %zu triangles, closed %s, hole-cap triangles %zu)\n",
                path.c_str(), mesh->vertex_count(), mesh->triangle_count(), src->is_closed() ? "yes" : "no",
                src->cap_triangle_count());
    static const char* const kInside[] = {"none (open mesh)", "first-hit facing", "parity of all crossings"};
    std::printf("inside test          %s\n", kInside[int(src->inside_test())]);
    std::printf("setup (scene+grid)   %.3f s\n", build);
    std::printf("embree bvh bytes     %zu (device total %zu)\n", src->bvh_bytes(), src->device_bytes());
    std::printf("rays, threads        %llu, %u (best of %u)\n", (unsigned long long)st.rays, st.threads,
                repeats);
    std::printf("generate             %.4f s  %.3f Mrays/s\n", st.seconds, st.rays_per_second * 1e-6);
    std::printf("plain rtcIntersect1  %.4f s  %.3f Mrays/s\n", st.plain_seconds,
                st.plain_rtcintersect_rays_per_second * 1e-6);
    std::printf("ratio                %.3f\n", st.ratio);
    std::printf("cpu time             generate %.4f s, plain %.4f s, ratio %.3f\n", st.cpu_seconds,
                st.plain_cpu_seconds, st.cpu_ratio);
    std::printf(
        "packet rtcIntersect16 %.4f s  %.3f Mrays/s (cpu %.4f s); generate vs packet: ratio %.3f, cpu %.3f\n",
        st.packet_seconds, st.packet_rays_per_second * 1e-6, st.packet_cpu_seconds, st.packet_ratio,
        st.packet_cpu_ratio);
    std::printf("load average (1 min) %.2f\n", load1);
    std::printf("interior candidates  %llu for %llu interior rays, parity rays %llu, fallbacks %llu\n",
                (unsigned long long)c.interior_candidates, (unsigned long long)((rays + 1) / 3),
                (unsigned long long)c.parity_queries, (unsigned long long)c.interior_fallbacks);
    if (!src->last_error().empty()) std::printf("embree errors        %s\n", src->last_error().c_str());
    return 0;
}
