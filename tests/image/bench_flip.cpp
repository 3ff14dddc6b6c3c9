// bench_flip [size=512] [repeats=5]: wall time of lsnif::image::flip on a size x size pair
// (a smooth colour image and a copy with noise and a shifted block), best and mean of the
// repeats. Not a CTest test: timings belong to BENCHMARKS-style runs, not to pass/fail.
#include <lsnif/image/flip.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>

int main(int argc, char** argv) {
    const auto size = static_cast<std::uint32_t>(argc > 1 ? std::atoi(argv[1]) : 512);
    const int repeats = argc > 2 ? std::atoi(argv[2]) : 5;
    if (size == 0 || repeats <= 0) {
        std::fprintf(stderr, "usage: bench_flip [size>0] [repeats>0]\n");
        return 2;
    }
    lsnif::image::Image a{size, size, std::vector<float>(3ull * size * size)};
    for (std::uint32_t y = 0; y < size; ++y)
        for (std::uint32_t x = 0; x < size; ++x)
            for (int c = 0; c < 3; ++c)
                a.rgb[3 * (std::size_t(y) * size + x) + c] =
                    0.5f + 0.4f * std::sin(0.05f * float(x) * float(c + 1)) * std::cos(0.03f * float(y));
    lsnif::image::Image b = a;
    std::mt19937 rng(7);
    std::normal_distribution<float> noise(0.0f, 0.03f);
    for (float& v : b.rgb) v = std::clamp(v + noise(rng), 0.0f, 1.0f);
    double best = 1e30, total = 0, mean_flip = 0;
    for (int r = 0; r < repeats; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
        auto result = lsnif::image::flip(a, b);
        const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (!result) {
            std::fprintf(stderr, "bench_flip: %s\n", result.error().message.c_str());
            return 1;
        }
        mean_flip = result->stats.mean;
        best = std::min(best, s);
        total += s;
    }
    std::printf("flip %ux%u at 67 ppd: best %.4f s, mean %.4f s over %d runs (mean FLIP %.4f)\n", size, size,
                best, total / repeats, repeats, mean_flip);
    return 0;
}
