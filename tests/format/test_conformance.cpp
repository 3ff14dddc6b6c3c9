// The reader against the conformance vectors of FORMAT.md §9 (schema/conformance/): exact
// conformance (§8.8) of the fp32 reference through the C API and of each stage (walk, logit)
// through the forward pass, and the tolerances of §8.8 for the reduced arithmetics this CPU
// runs. In the portable build (scripts/test) the same cases check the portable code.
#include <doctest/doctest.h>
#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "../test_data.hpp"

namespace {

using namespace lsnif::format;
namespace fs = std::filesystem;

// One line of a vector file (FORMAT.md §9).
struct Vector {
    std::string family;
    Ray ray;
    std::string classification;
    std::uint32_t count = 0;
    std::vector<std::uint32_t> voxels;
    bool evaluated = false;
    float logit = 0;
    lsnif_hit hit{};
};

float from_hex(const std::string& s) {
    return std::bit_cast<float>(std::uint32_t(std::stoul(s, nullptr, 16)));
}

std::uint32_t bits(float f) {
    return std::bit_cast<std::uint32_t>(f);
}

std::vector<Vector> read_vectors(const fs::path& path) {
    std::ifstream in(path);
    REQUIRE_MESSAGE(in, (path.string() + ": cannot open"));
    std::string line;
    std::getline(in, line);
    REQUIRE_MESSAGE(line == "lsnif-conformance 1", (path.string() + ": not a vector file"));
    std::vector<Vector> out;
    while (std::getline(in, line)) {
        std::istringstream fields(line);
        std::vector<std::string> f;
        for (std::string s; fields >> s;) f.push_back(s);
        REQUIRE_MESSAGE(f.size() == 19, (path.string() + ": a line without 19 fields: " + line));
        Vector v;
        v.family = f[0];
        float r[8];
        for (int k = 0; k < 8; ++k) r[k] = from_hex(f[1 + k]);
        v.ray = Ray{{r[0], r[1], r[2]}, r[3], {r[4], r[5], r[6]}, r[7]};
        v.classification = f[9];
        v.count = std::uint32_t(std::stoul(f[10]));
        if (f[11] != "-") {
            std::istringstream list(f[11]);
            for (std::string s; std::getline(list, s, ',');) v.voxels.push_back(std::uint32_t(std::stoul(s)));
        }
        v.evaluated = f[12] != "-";
        if (v.evaluated) v.logit = from_hex(f[12]);
        v.hit.hit = std::uint32_t(std::stoul(f[13]));
        v.hit.t = from_hex(f[14]);
        for (int a = 0; a < 3; ++a) v.hit.normal[a] = from_hex(f[15 + a]);
        v.hit.material = std::uint32_t(std::stoul(f[18]));
        out.push_back(v);
    }
    return out;
}

fs::path conformance_dir() {
    return LSNIF_CONFORMANCE_DIR;
}

const char* const kAssets[] = {"armadillo_fp16", "peterbilt_fp16", "peterbilt_u8", "synthetic_materials"};

struct Opened {
    lsnif_model* model = nullptr;
    explicit Opened(const fs::path& p) {
        lsnif_error e{};
        REQUIRE_MESSAGE(lsnif_open_file(p.string().c_str(), &model, &e) == LSNIF_OK, e.message);
    }
    ~Opened() { lsnif_close(model); }
};

std::vector<lsnif_hit> intersect(lsnif_model* model, const std::vector<Vector>& vs) {
    std::vector<lsnif_ray> rays(vs.size());
    for (std::size_t i = 0; i < vs.size(); ++i) std::memcpy(&rays[i], &vs[i].ray, sizeof(lsnif_ray));
    std::vector<lsnif_hit> hits(vs.size());
    REQUIRE(lsnif_intersect(model, rays.data(), rays.size(), hits.data()) == LSNIF_OK);
    return hits;
}

}  // namespace

TEST_CASE("the vector files cover every case of FORMAT.md §9 and every classification") {
    for (const char* name : kAssets) {
        const auto vs = read_vectors(conformance_dir() / (std::string(name) + ".rays"));
        std::vector<std::string> families, classes;
        std::size_t hits = 0, evaluated = 0;
        for (const Vector& v : vs) {
            families.push_back(v.family);
            classes.push_back(v.classification);
            hits += v.hit.hit;
            evaluated += v.evaluated;
        }
        for (const char* f :
             {"outside", "from_surface", "same_origin", "axis", "corner", "on_box", "bounded", "degenerate"})
            CHECK_MESSAGE(std::count(families.begin(), families.end(), f) > 0, std::string(name), " lacks ",
                          std::string(f));
        for (const char* c : {"ok", "miss", "invalid"})
            CHECK_MESSAGE(std::count(classes.begin(), classes.end(), c) > 0, std::string(name), " lacks ",
                          std::string(c));
        // Both answers of the network, many times each.
        CHECK(hits > 100);
        CHECK(evaluated - hits > 30);
    }
}

TEST_CASE("the fp32 reader reproduces every conformance vector bit for bit") {
    for (const char* name : kAssets) {
        const std::string asset = name;
        CAPTURE(asset);
        const auto vs = read_vectors(conformance_dir() / (std::string(name) + ".rays"));
        Opened m(conformance_dir() / (std::string(name) + ".lsnif"));
        lsnif_arithmetic in_use{};
        REQUIRE(lsnif_set_arithmetic(m.model, LSNIF_ARITHMETIC_FP32, &in_use) == LSNIF_OK);
        REQUIRE(in_use == LSNIF_ARITHMETIC_FP32);
        const auto hits = intersect(m.model, vs);
        std::vector<lsnif_ray> rays(vs.size());
        for (std::size_t i = 0; i < vs.size(); ++i) std::memcpy(&rays[i], &vs[i].ray, sizeof(lsnif_ray));
        std::vector<std::uint8_t> occluded(vs.size());
        REQUIRE(lsnif_occluded(m.model, rays.data(), rays.size(), occluded.data()) == LSNIF_OK);
        int wrong = 0;
        for (std::size_t i = 0; i < vs.size(); ++i) {
            const lsnif_hit& want = vs[i].hit;
            const lsnif_hit& got = hits[i];
            bool same = got.hit == want.hit && bits(got.t) == bits(want.t) && occluded[i] == want.hit;
            if (want.hit)
                same = same && got.material == want.material && bits(got.normal[0]) == bits(want.normal[0]) &&
                       bits(got.normal[1]) == bits(want.normal[1]) &&
                       bits(got.normal[2]) == bits(want.normal[2]);
            if (!same && ++wrong <= 5)
                FAIL_CHECK(std::string(name), " ray ", i, " (", vs[i].family, ") differs");
        }
        CHECK(wrong == 0);
        // Alone, each ray gets the same answer as in the batch.
        for (std::size_t i = 0; i < vs.size(); i += 7) {
            lsnif_hit h{};
            REQUIRE(lsnif_intersect(m.model, &rays[i], 1, &h) == LSNIF_OK);
            CHECK(bits(h.t) == bits(hits[i].t));
        }
    }
}

TEST_CASE("each stage of the forward pass reproduces the vectors: walk, points and logit") {
    for (const char* name : kAssets) {
        const std::string asset = name;
        CAPTURE(asset);
        const auto vs = read_vectors(conformance_dir() / (std::string(name) + ".rays"));
        auto bytes = read_file_bytes((conformance_dir() / (std::string(name) + ".lsnif")).string());
        REQUIRE(bytes.ok());
        auto model = read_model(*bytes);
        REQUIRE(model.ok());
        const Runtime rt = make_runtime(*model, MlpArithmetic::fp32);
        const auto grid = rt.grid_views();
        std::vector<Ray> rays;
        for (const Vector& v : vs) rays.push_back(v.ray);
        std::vector<RayPoints> batch(rays.size());
        std::vector<TraceStatus> status(rays.size());
        trace_points_batch(rt.geo, rt.occupancy, rays, batch.data(), status.data());
        std::vector<float> row(rt.geo.input_width), scratch;
        int wrong = 0;
        for (std::size_t i = 0; i < vs.size(); ++i) {
            const Vector& v = vs[i];
            RayPoints pts;
            const TraceStatus s = trace_points(rt.geo, model->occupancy.data(), v.ray, pts);
            const char* cls = s == TraceStatus::ok ? "ok" : s == TraceStatus::miss ? "miss" : "invalid";
            bool same = v.classification == cls && status[i] == s && pts.count == v.count &&
                        batch[i].count == v.count;
            for (std::uint32_t k = 0; same && k < pts.count; ++k)
                same = pts.voxel[k] == v.voxels[k] && batch[i].voxel[k] == v.voxels[k];
            if (same && v.evaluated) {
                encode_points(rt.geo, grid.data(), pts, row.data());
                const float* o = mlp_forward(rt.net, row.data(), 1, scratch);
                same = bits(o[OutputLayout::visibility]) == bits(v.logit);
            }
            same = same && v.evaluated == (pts.count > 0);
            if (!same && ++wrong <= 5) FAIL_CHECK(std::string(name), " ray ", i, " (", v.family, ") differs");
        }
        CHECK(wrong == 0);
    }
}

// FORMAT.md §8.8's tolerances, met by the reduced arithmetics of this CPU (none where it has
// neither: the fp32 case above is then the whole check).
TEST_CASE("the reduced arithmetics meet the tolerances of FORMAT.md §8.8 on the vectors") {
    int checked = 0;
    for (const lsnif_arithmetic arithmetic : {LSNIF_ARITHMETIC_BF16, LSNIF_ARITHMETIC_INT8}) {
        for (const char* name : kAssets) {
            const std::string asset = name;
            CAPTURE(asset);
            const auto vs = read_vectors(conformance_dir() / (std::string(name) + ".rays"));
            Opened m(conformance_dir() / (std::string(name) + ".lsnif"));
            lsnif_arithmetic in_use{};
            REQUIRE(lsnif_set_arithmetic(m.model, arithmetic, &in_use) == LSNIF_OK);
            if (in_use != arithmetic) continue;
            const std::string arithmetic_name = lsnif_arithmetic_string(arithmetic);
            CAPTURE(arithmetic_name);
            ++checked;
            const auto hits = intersect(m.model, vs);
            lsnif_info info{};
            REQUIRE(lsnif_get_info(m.model, &info) == LSNIF_OK);
            const double D =
                std::sqrt(double(info.box_max[0] - info.box_min[0]) * (info.box_max[0] - info.box_min[0]) +
                          double(info.box_max[1] - info.box_min[1]) * (info.box_max[1] - info.box_min[1]) +
                          double(info.box_max[2] - info.box_min[2]) * (info.box_max[2] - info.box_min[2]));
            std::size_t evaluated = 0, agree = 0, both = 0, t_close = 0;
            std::vector<double> angles;  // degrees between the normals of common hits
            for (std::size_t i = 0; i < vs.size(); ++i) {
                const Vector& v = vs[i];
                if (!v.evaluated) {
                    CHECK(hits[i].hit == 0);
                    continue;
                }
                ++evaluated;
                agree += hits[i].hit == v.hit.hit;
                if (std::fabs(v.logit) >= 1.0f)
                    CHECK_MESSAGE(hits[i].hit == v.hit.hit, "ray ", i, " logit ", v.logit);
                if (!(hits[i].hit && v.hit.hit)) continue;
                ++both;
                const Ray& r = v.ray;
                const double dl = std::sqrt(double(r.dir[0]) * r.dir[0] + double(r.dir[1]) * r.dir[1] +
                                            double(r.dir[2]) * r.dir[2]);
                t_close += std::fabs(double(hits[i].t) - v.hit.t) * dl / D <= 0.01;
                double dot = 0;
                for (int a = 0; a < 3; ++a) dot += double(hits[i].normal[a]) * v.hit.normal[a];
                angles.push_back(std::acos(std::clamp(dot, -1.0, 1.0)) * 180 / M_PI);
            }
            REQUIRE(both > 100);
            std::sort(angles.begin(), angles.end());
            const double median = angles[both / 2], p90 = angles[both * 9 / 10];
            MESSAGE(std::string(name), " ", std::string(lsnif_arithmetic_string(arithmetic)), ": decisions ",
                    agree, "/", evaluated, ", distances within D/100 ", t_close, "/", both,
                    ", normal angle median ", median, " deg, 90th percentile ", p90, " deg");
            CHECK(agree >= 0.995 * evaluated);
            CHECK(t_close >= 0.99 * both);
            CHECK(median <= 2.0);
            CHECK(p90 <= 10.0);
        }
    }
    if (!checked) MESSAGE("this CPU runs neither reduced arithmetic: only fp32 was checked");
}
