// Real-asset rays for the reader's tests: a model opened through the C API, and rays from
// outside onto it with, from each of their hits, ambient-occlusion rays leaving the surface.
#pragma once
#include <doctest/doctest.h>
#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

#include <cmath>
#include <filesystem>
#include <random>
#include <utility>
#include <vector>

namespace lsnif_test {

// A model opened through the C API; closed on scope exit.
struct OpenModel {
    lsnif_model* model = nullptr;
    explicit OpenModel(const std::filesystem::path& path) {
        REQUIRE(lsnif_open_file(path.string().c_str(), &model, nullptr) == LSNIF_OK);
    }
    ~OpenModel() { lsnif_close(model); }
    OpenModel(const OpenModel&) = delete;
    OpenModel& operator=(const OpenModel&) = delete;
};

// The asset's runtime read from its file by the format library directly: what the reader
// holds behind the C API, for tests that trace or inspect it themselves.
inline lsnif::format::Runtime runtime_of(const std::filesystem::path& path) {
    const auto bytes = lsnif::format::read_file_bytes(path.string());
    REQUIRE(bytes.ok());
    auto data = lsnif::format::read_model(bytes.value());
    REQUIRE(data.ok());
    return lsnif::format::make_runtime(std::move(data.value()));
}

// Rays from outside the box towards its middle third, and, from each of their hits, 16
// ambient-occlusion rays over the hemisphere of the returned normal: 1e-4 of the box
// diagonal off the surface, a tenth of the diagonal long (as lsnif eval's). `outside` gets
// the first kind, `leaving` the second.
inline void make_rays(lsnif_model* model, std::vector<lsnif_ray>& outside, std::vector<lsnif_ray>& leaving) {
    lsnif_info info{};
    REQUIRE(lsnif_get_info(model, &info) == LSNIF_OK);
    float c[3], d = 0;
    for (int a = 0; a < 3; ++a) {
        c[a] = 0.5f * (info.box_min[a] + info.box_max[a]);
        const float e = info.box_max[a] - info.box_min[a];
        d += e * e;
    }
    d = std::sqrt(d);
    std::mt19937 rng(5);
    std::normal_distribution<float> nd;
    std::uniform_real_distribution<float> ud(-0.5f, 0.5f);
    const auto unit = [&](float v[3]) {
        const float l = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
        for (int a = 0; a < 3; ++a) v[a] /= l;
    };
    outside.resize(4096);
    for (lsnif_ray& r : outside) {
        float v[3] = {nd(rng), nd(rng), nd(rng)};
        unit(v);
        for (int a = 0; a < 3; ++a) {
            r.org[a] = c[a] + v[a] * d;
            r.dir[a] = c[a] + ud(rng) * 0.3f * d - r.org[a];
        }
        unit(r.dir);
        r.tmin = 0;
        r.tmax = INFINITY;
    }
    std::vector<lsnif_hit> hits(outside.size());
    REQUIRE(lsnif_intersect(model, outside.data(), outside.size(), hits.data()) == LSNIF_OK);
    for (std::size_t i = 0; i < outside.size(); ++i) {
        if (!hits[i].hit) continue;
        const float* n = hits[i].normal;
        const float side =
            n[0] * outside[i].dir[0] + n[1] * outside[i].dir[1] + n[2] * outside[i].dir[2] > 0 ? -1.f : 1.f;
        for (int k = 0; k < 16; ++k) {
            lsnif_ray r{};
            float v[3] = {nd(rng), nd(rng), nd(rng)};
            unit(v);
            if ((v[0] * n[0] + v[1] * n[1] + v[2] * n[2]) * side < 0)
                for (float& x : v) x = -x;
            for (int a = 0; a < 3; ++a) {
                r.dir[a] = v[a];
                r.org[a] = outside[i].org[a] + hits[i].t * outside[i].dir[a] + side * n[a] * 1e-4f * d;
            }
            r.tmin = 0;
            r.tmax = 0.1f * d;
            leaving.push_back(r);
        }
    }
}

}  // namespace lsnif_test
