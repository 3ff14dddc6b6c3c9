// measure_throughput(): the cost of ground-truth generation against plain Embree tracing
// of the very same rays (one rtcIntersect1 per ray, and for comparison Embree's 16-wide
// packets), with the same threads and work split, in wall and in process CPU time. Apart
// from generation because it is a benchmark: it only reads the scene, and nothing in the
// conversion depends on its numbers.
#include "sampling_internal.hpp"

#include <lsnif/base/clock.hpp>

#include <chrono>
#include <ctime>

namespace lsnif::sampling {

namespace {

using base::seconds_since;

// CPU time of the whole process (every thread), in seconds.
double process_cpu_seconds() {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

// Best times (seconds) of each contender over the repeats.
struct BestTimes {
    double gen = INFINITY, plain = INFINITY, packet = INFINITY;
    double gen_cpu = INFINITY, plain_cpu = INFINITY, packet_cpu = INFINITY;
};

// Runs `work` once; lowers `wall` and `cpu` to its wall and process CPU time if smaller.
template <class Work>
void time_best(double& wall, double& cpu, Work&& work) {
    const auto t0 = std::chrono::steady_clock::now();
    const double c0 = process_cpu_seconds();
    work();
    wall = std::min(wall, seconds_since(t0));
    cpu = std::min(cpu, process_cpu_seconds() - c0);
}

GenerationStats stats_from(const BestTimes& b, std::size_t count, std::uint32_t threads) {
    GenerationStats st;
    st.rays = count;
    st.threads = threads;
    st.seconds = b.gen;
    st.rays_per_second = double(count) / b.gen;
    st.plain_seconds = b.plain;
    st.plain_rtcintersect_rays_per_second = double(count) / b.plain;
    st.ratio = st.rays_per_second / st.plain_rtcintersect_rays_per_second;
    st.cpu_seconds = b.gen_cpu;
    st.plain_cpu_seconds = b.plain_cpu;
    st.cpu_ratio = b.gen_cpu > 0 ? b.plain_cpu / b.gen_cpu : 0;
    st.packet_seconds = b.packet;
    st.packet_rays_per_second = double(count) / b.packet;
    st.packet_ratio = st.rays_per_second / st.packet_rays_per_second;
    st.packet_cpu_seconds = b.packet_cpu;
    st.packet_cpu_ratio = b.gen_cpu > 0 ? b.packet_cpu / b.gen_cpu : 0;
    return st;
}

}  // namespace

GenerationStats measure_throughput(EmbreeSource& src, std::uint64_t seed, std::size_t count,
                                   std::uint32_t repeats) {
    const std::uint32_t threads = src.threads();
    if (count == 0) {
        GenerationStats st;
        st.threads = threads;
        return st;
    }
    repeats = std::max<std::uint32_t>(1, repeats);
    const EmbreeSource::Impl& m = *src.impl_;
    std::vector<samples::Sample> samples;
    // The baselines' answers are stored (not decoded), so that their work is not optimized away.
    std::vector<EmbreeSource::Impl::RawHit> plain(count), packet(count);
    BestTimes best;
    for (std::uint32_t r = 0; r < repeats; ++r) {
        time_best(best.gen, best.gen_cpu, [&] { src.generate(seed, count, samples, nullptr); });
        // The baseline: the same rays, one rtcIntersect1 each, same threads and chunks.
        time_best(best.plain, best.plain_cpu, [&] {
            parallel_chunks(count, threads, [&](std::size_t b, std::size_t e) {
                RTCIntersectContext ctx;
                rtcInitIntersectContext(&ctx);
                for (std::size_t i = b; i < e; ++i) {
                    const format::Ray& ray = samples[i].ray;
                    RTCRayHit rh = make_ray_hit(ray.org, ray.dir, ray.tmin, ray.tmax, kMeshMask);
                    rtcIntersect1(m.scene, &ctx, &rh);
                    plain[i] = {rh.ray.tfar, rh.hit.u, rh.hit.v,
                                rh.hit.geomID == RTC_INVALID_GEOMETRY_ID ? kNoPrimitive : rh.hit.primID};
                }
            });
        });
        // For comparison only: the same rays through Embree's 16-wide packet interface.
        time_best(best.packet, best.packet_cpu, [&] {
            parallel_chunks(count, threads, [&](std::size_t b, std::size_t e) {
                m.intersect_packets(samples.data() + b, e - b, packet.data() + b);
            });
        });
    }
    return stats_from(best, count, threads);
}

}  // namespace lsnif::sampling
