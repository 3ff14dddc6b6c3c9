// A C++ renderer's use of the installed reader (RAII ownership, std::vector batches): the
// header's extern "C" block is what it relies on. Opens an asset, traces a fixed fan of
// rays with the fp32 reference arithmetic and prints the library version and what came
// back. tests/install/check_install.sh builds it against installed trees and packages
// and compares its output with the same program built in the project's tree.
// Usage: lsnif_consumer_cpp FILE.lsnif
#include <lsnif/lsnif.h>

#include <cmath>
#include <cstdio>
#include <memory>
#include <vector>

namespace {

struct ModelCloser {
    void operator()(lsnif_model* model) const { lsnif_close(model); }
};
using ModelPtr = std::unique_ptr<lsnif_model, ModelCloser>;

constexpr int fan = 16;

std::vector<lsnif_ray> fan_through_box(const lsnif_info& info) {
    const float* lo = info.box_min;
    const float* hi = info.box_max;
    std::vector<lsnif_ray> rays;
    rays.reserve(fan * fan);
    for (int i = 0; i < fan; ++i) {
        for (int j = 0; j < fan; ++j) {
            float u = (i + 0.5f) / fan, v = (j + 0.5f) / fan;
            float target[3] = {lo[0] + u * (hi[0] - lo[0]), lo[1] + v * (hi[1] - lo[1]), hi[2]};
            lsnif_ray r{};
            r.org[0] = 0.5f * (lo[0] + hi[0]);
            r.org[1] = 0.5f * (lo[1] + hi[1]);
            r.org[2] = lo[2] - (hi[2] - lo[2]);
            for (int k = 0; k < 3; ++k) r.dir[k] = target[k] - r.org[k];
            r.tmin = 0.0f;
            r.tmax = INFINITY;
            rays.push_back(r);
        }
    }
    return rays;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: %s FILE.lsnif\n", argv[0]);
        return 2;
    }
    lsnif_model* raw = nullptr;
    lsnif_error err;
    lsnif_status st = lsnif_open_file(argv[1], &raw, &err);
    if (st != LSNIF_OK) {
        std::fprintf(stderr, "error: %s: %s (%s)\n", argv[1], err.message, lsnif_status_string(st));
        return 1;
    }
    ModelPtr model(raw);
    lsnif_set_arithmetic(model.get(), LSNIF_ARITHMETIC_FP32, nullptr);
    lsnif_info info;
    lsnif_get_info(model.get(), &info);

    std::vector<lsnif_ray> rays = fan_through_box(info);
    std::vector<lsnif_hit> hits(rays.size());
    st = lsnif_intersect(model.get(), rays.data(), rays.size(), hits.data());
    if (st != LSNIF_OK) {
        std::fprintf(stderr, "error: %s: intersect failed (%s)\n", argv[1], lsnif_status_string(st));
        return 1;
    }
    int hit_count = 0;
    double t_sum = 0.0;
    for (const lsnif_hit& h : hits) {
        if (!h.hit) continue;
        ++hit_count;
        t_sum += h.t;
    }
    uint32_t major = 0, minor = 0;
    const char* library = lsnif_version(&major, &minor);
    std::printf("library %s reads %u.%u\n", library, unsigned(major), unsigned(minor));
    std::printf("grid %u^3, %u levels, mlp %u -> %u\n", info.grid_resolution, info.level_count,
                info.input_width, info.output_count);
    std::printf("%d of %d rays hit, mean t %.4f\n", hit_count, int(rays.size()),
                hit_count ? t_sum / hit_count : 0.0);
    return 0;
}
