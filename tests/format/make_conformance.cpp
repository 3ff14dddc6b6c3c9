// lsnif_make_conformance: writes the conformance vectors of schema/FORMAT.md §9 (the files in
// schema/conformance/) and the 8-bit copy of an asset they use. A maintainer's tool, run by
// scripts/make_conformance; the test suite only reads what it wrote.
//
//   lsnif_make_conformance quantize IN.lsnif OUT.lsnif
//       OUT: IN with its grid stored as 8-bit affine features (FORMAT.md §6.4.1).
//   lsnif_make_conformance synthetic OUT.lsnif
//       OUT: an untrained model with what no converted asset has: material logits, the
//       segment distance encoding, the direction input alone, dense levels only.
//   lsnif_make_conformance vectors ASSET.lsnif OUT.rays SEED
//       OUT: rays of every case of §9 with the fp32 reference's outputs on them.
//
// The expected outputs come from the reader's fp32 arithmetic (the reference of §8.6), and
// are checked here against the C API's lsnif_intersect before they are written.
#include <lsnif/lsnif.h>
#include <lsnif/base/random.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

namespace {

using namespace lsnif::format;
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

struct Case {
    std::string name;
    Ray ray;
};

// The generator's view of an asset: its geometry and the voxels a ray can hit.
struct Asset {
    Geometry geo;
    std::vector<std::uint8_t> occupancy;
    std::vector<std::uint32_t> occupied;  // linear voxel indices
};

// Object-space position of grid coordinate g on axis a, rounded to f32 (make_ray_grid maps
// it back exactly in almost every case; the vectors record what the reference computes).
float object_at(const Geometry& geo, int a, double g) {
    const double cell = (double(geo.box_max[a]) - geo.box_min[a]) / geo.V;
    return float(geo.box_min[a] + g * cell);
}

void voxel_xyz(const Geometry& geo, std::uint32_t v, std::uint32_t xyz[3]) {
    xyz[0] = v % geo.V;
    xyz[1] = (v / geo.V) % geo.V;
    xyz[2] = v / (geo.V * geo.V);
}

struct Generator {
    const Asset& asset;
    lsnif::base::SplitMix64 rng;
    std::vector<Case> out;

    float u(float lo, float hi) { return rng.uniform(lo, hi); }
    std::uint32_t below(std::uint32_t n) { return std::uint32_t(rng.next() % n); }
    void unit(float d[3]) {
        do {
            for (int a = 0; a < 3; ++a) d[a] = u(-1.0f, 1.0f);
        } while (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] > 1.0f ||
                 d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < 1e-4f);
    }
    // A point inside a random occupied voxel, in grid coordinates.
    void in_occupied(double g[3]) {
        std::uint32_t xyz[3];
        voxel_xyz(asset.geo, asset.occupied[below(std::uint32_t(asset.occupied.size()))], xyz);
        for (int a = 0; a < 3; ++a) g[a] = xyz[a] + double(u(0.05f, 0.95f));
    }
    // The ray from grid point g along grid-space direction d, in object space.
    Ray from_grid(const double g[3], const float d[3], float tmin, float tmax) {
        const Geometry& geo = asset.geo;
        Ray r{};
        for (int a = 0; a < 3; ++a) {
            r.org[a] = object_at(geo, a, g[a]);
            r.dir[a] = float(d[a] * ((double(geo.box_max[a]) - geo.box_min[a]) / geo.V));
        }
        r.tmin = tmin;
        r.tmax = tmax;
        return r;
    }
    void add(const char* name, const Ray& r) { out.push_back({name, r}); }
    // An unbounded ray through a random point of an occupied voxel, starting `back` voxels
    // before it along a random direction.
    Ray through_occupied(double back) {
        double g[3];
        in_occupied(g);
        float d[3];
        unit(d);
        const double o[3] = {g[0] - d[0] * back, g[1] - d[1] * back, g[2] - d[2] * back};
        return from_grid(o, d, 0.0f, kInf);
    }

    // Rays from outside the box through a point of an occupied voxel: primary-like rays.
    void outside(int n) {
        for (int i = 0; i < n; ++i) add("outside", through_occupied(2.0 * asset.geo.V));
    }
    // Rays leaving a point of an occupied voxel, bounded (ambient occlusion) or not.
    void from_surface(int n) {
        for (int i = 0; i < n; ++i) {
            double g[3];
            in_occupied(g);
            float d[3];
            unit(d);
            add("from_surface", from_grid(g, d, 0.0f, i % 2 ? kInf : u(0.5f, 8.0f)));  // t in voxels
        }
    }
    // Three rays leaving one point one after the other (a shading point's rays).
    void same_origin(int n) {
        for (int i = 0; i < n; i += 3) {
            double g[3];
            in_occupied(g);
            for (int k = 0; k < 3; ++k) {
                float d[3];
                unit(d);
                add("same_origin", from_grid(g, d, 0.0f, kInf));
            }
        }
    }
    // Axis-parallel rays along lattice planes and edges of the voxel grid (integer grid
    // coordinates on the two other axes), from outside the box or from inside.
    void axis(int n) {
        const Geometry& geo = asset.geo;
        for (int i = 0; i < n; ++i) {
            const int a = int(below(3));
            double g[3];
            in_occupied(g);
            const int planes = int(below(3));  // 0: none on a plane, 1: a face, 2: an edge
            for (int k = 1; k <= planes; ++k) g[(a + k) % 3] = std::round(g[(a + k) % 3]);
            float d[3] = {0, 0, 0};
            d[a] = i % 2 ? 1.0f : -1.0f;
            if (i % 4 < 2) g[a] = d[a] > 0 ? -1.5 : geo.V + 1.5;  // from outside
            add("axis", from_grid(g, d, 0.0f, kInf));
        }
    }
    // Diagonal rays through lattice vertices of the grid (voxel corners), from outside.
    void corner(int n) {
        const Geometry& geo = asset.geo;
        for (int i = 0; i < n; ++i) {
            std::uint32_t xyz[3];
            voxel_xyz(geo, asset.occupied[below(std::uint32_t(asset.occupied.size()))], xyz);
            float d[3];
            for (int a = 0; a < 3; ++a) d[a] = below(2) ? 1.0f : -1.0f;
            if (i % 3 == 0) d[below(3)] = 0.0f;  // through an edge of the lattice instead
            double g[3];
            for (int a = 0; a < 3; ++a) g[a] = double(xyz[a]) - d[a] * 0.5 * geo.V;
            add("corner", from_grid(g, d, 0.0f, kInf));
        }
    }
    // Rays starting exactly on a face of the box, entering or leaving it.
    void on_box(int n) {
        const Geometry& geo = asset.geo;
        for (int i = 0; i < n; ++i) {
            double g[3];
            in_occupied(g);
            const int a = int(below(3));
            const bool low = below(2);
            g[a] = low ? 0.0 : geo.V;
            float d[3];
            unit(d);
            if ((d[a] > 0) != low) d[a] = -d[a];  // into the box, except every fourth
            if (i % 4 == 3) d[a] = -d[a];
            Ray r = from_grid(g, d, 0.0f, kInf);
            r.org[a] = low ? geo.box_min[a] : geo.box_max[a];
            add("on_box", r);
        }
    }
    // Segments that start or end inside the box: tmin past the origin, tmax inside an
    // occupied voxel or exactly on a voxel face.
    void bounded(int n) {
        for (int i = 0; i < n; ++i) {
            const double back = 0.75 * asset.geo.V;
            Ray r = through_occupied(back);
            const float t_point = float(back);  // where the occupied point is
            switch (i % 3) {
                case 0: r.tmax = t_point; break;
                case 1: r.tmin = t_point; break;
                default: r.tmin = 0.5f * t_point, r.tmax = 1.02f * t_point; break;
            }
            add("bounded", r);
        }
    }
    // Rays the reader must reject or can answer without the grid: invalid rays (§8.2),
    // empty segments, misses of the box, directions that are zero on some axes.
    void degenerate() {
        const Geometry& geo = asset.geo;
        double g[3];
        in_occupied(g);
        const float d[3] = {0.6f, -0.48f, 0.64f};
        Ray base = from_grid(g, d, 0.0f, kInf);
        std::copy(d, d + 3, base.dir);
        const auto with = [&](const char* name, auto&& change) {
            Ray r = base;
            change(r);
            add(name, r);
        };
        with("degenerate", [](Ray& r) { r.dir[0] = r.dir[1] = r.dir[2] = 0.0f; });
        with("degenerate", [](Ray& r) { r.dir[0] = r.dir[1] = r.dir[2] = -0.0f; });
        with("degenerate", [](Ray& r) { r.org[1] = kNaN; });
        with("degenerate", [](Ray& r) { r.org[2] = kInf; });
        with("degenerate", [](Ray& r) { r.dir[0] = -kInf; });
        with("degenerate", [](Ray& r) { r.dir[2] = kNaN; });
        with("degenerate", [](Ray& r) { r.tmin = kNaN; });
        with("degenerate", [](Ray& r) { r.tmax = kNaN; });
        with("degenerate", [](Ray& r) { r.tmin = 2.0f, r.tmax = 1.0f; });
        with("degenerate", [](Ray& r) { r.tmin = r.tmax = 0.0f; });
        with("degenerate", [](Ray& r) { r.tmin = -kInf; });
        with("degenerate", [](Ray& r) { r.dir[0] = 1e-45f, r.dir[1] = 1e-45f, r.dir[2] = 0.0f; });
        with("degenerate", [](Ray& r) { r.dir[1] = 1e20f; });
        with("degenerate", [](Ray& r) { r.dir[0] = 3e-19f, r.dir[1] = 0.0f, r.dir[2] = 0.0f; });
        with("degenerate", [](Ray& r) { r.dir[0] = 1e-30f, r.dir[1] = 1.0f, r.dir[2] = 0.0f; });
        with("degenerate", [&](Ray& r) {  // x subnormal in grid units, from a grid plane: invalid
            const double cell = (double(geo.box_max[0]) - geo.box_min[0]) / geo.V;
            r.org[0] = object_at(geo, 0, std::floor(g[0]));
            r.dir[0] = float(1e-40 * cell), r.dir[1] = 1.0f, r.dir[2] = 0.0f;
        });
        with("degenerate", [&](Ray& r) {  // parallel to x, outside the box in y: a miss
            r.dir[0] = 1.0f, r.dir[1] = r.dir[2] = 0.0f;
            r.org[1] = geo.box_max[1] + 1.0f;
        });
        with("degenerate", [&](Ray& r) {  // pointing away from the box
            for (int a = 0; a < 3; ++a) r.org[a] = geo.box_max[a] + 1.0f, r.dir[a] = 1.0f;
        });
        with("degenerate", [&](Ray& r) {  // ends before reaching the box
            for (int a = 0; a < 3; ++a) r.org[a] = geo.box_max[a] + 1.0f, r.dir[a] = -1.0f;
            r.tmax = 0.5f;
        });
    }
};

std::string hex(float f) {
    char s[16];
    std::snprintf(s, sizeof s, "%08x", std::bit_cast<std::uint32_t>(f));
    return s;
}

int fail(const std::string& message) {
    std::fprintf(stderr, "error: %s\n", message.c_str());
    return 1;
}

Result<ModelData> load_model(const std::string& path) {
    auto bytes = read_file_bytes(path);
    if (!bytes) return bytes.error();
    return read_model(*bytes);
}

int quantize(const std::string& in, const std::string& out) {
    auto model = load_model(in);
    if (!model) return fail(in + ": " + model.error().message);
    auto quantized = quantize_model(*model);
    if (!quantized) return fail(in + ": " + quantized.error().message);
    if (const Error e = write_file(out, *quantized)) return fail(out + ": " + e.message);
    return 0;
}

// A shell of occupied voxels and weights drawn so that every output varies with the input:
// features of magnitude 1, weights scaled by 2 / sqrt(inputs), small biases, except the
// visibility logit's, which makes hits and misses about as frequent.
constexpr float kVisibilityBias = 0.25f;
int synthetic(const std::string& out) {
    ModelDesc d;
    d.grid_resolution = 12;
    d.max_points = 6;
    d.level_resolution = {6, 12};  // 7^3 = 343 and 13^3 = 2197 <= 2^12: both dense
    d.features_per_level = 2;
    d.log2_table_size = 12;
    d.hidden_width = {24, 16};
    d.material_count = 3;
    d.distance_encoding = LSNIF_DISTANCE_SEGMENT;
    d.ray_inputs = kRayInputDirection;
    d.box_min = {-1.5f, -0.75f, 0.25f};
    d.box_max = {2.5f, 1.25f, 1.75f};
    auto empty = make_empty_model(d);
    if (!empty) return fail(empty.error().message);
    ModelData m = std::move(*empty);
    m.metadata_json = R"({"format": "lsnif-metadata/1", "object": {"name": "synthetic"}})";
    const std::uint32_t V = d.grid_resolution;
    const float c = 0.5f * float(V - 1), r = 0.35f * float(V);
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const float d2 = (x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c);
                if (d2 > r * r || d2 < (r - 1.5f) * (r - 1.5f)) continue;
                const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
            }
    lsnif::base::SplitMix64 rng{7};
    for (auto& level : m.grid)
        for (auto& h : level) h = float_to_half(rng.uniform(-1.0f, 1.0f));
    for (std::uint32_t k = 0; k < d.layer_count(); ++k) {
        const float scale = 2.0f / std::sqrt(float(d.layer_shape(k).second));
        for (auto& h : m.weights[k]) h = float_to_half(rng.uniform(-scale, scale));
        for (auto& h : m.biases[k]) h = float_to_half(rng.uniform(-0.1f, 0.1f));
    }
    m.biases.back()[OutputLayout::visibility] = float_to_half(kVisibilityBias);
    if (const Error e = write_file(out, m)) return fail(out + ": " + e.message);
    return 0;
}

const char* status_name(TraceStatus s) {
    return s == TraceStatus::ok ? "ok" : s == TraceStatus::miss ? "miss" : "invalid";
}

int vectors(const std::string& asset_path, const std::string& out_path, std::uint64_t seed) {
    auto model = load_model(asset_path);
    if (!model) return fail(asset_path + ": " + model.error().message);
    Asset asset;
    asset.geo = make_geometry(model->desc);
    asset.occupancy = model->occupancy;
    for (std::uint32_t v = 0; v < model->desc.voxel_count(); ++v)
        if ((asset.occupancy[v >> 3] >> (v & 7)) & 1u) asset.occupied.push_back(v);
    if (asset.occupied.empty()) return fail(asset_path + ": no occupied voxel");
    const Runtime rt = make_runtime(*model, MlpArithmetic::fp32);
    const std::vector<GridView> grid = rt.grid_views();

    Generator gen{asset, {seed}, {}};
    gen.outside(200);
    gen.from_surface(200);
    gen.same_origin(90);
    gen.axis(120);
    gen.corner(90);
    gen.on_box(60);
    gen.bounded(90);
    gen.degenerate();

    lsnif_model* reader = nullptr;
    lsnif_error error{};
    if (lsnif_open_file(asset_path.c_str(), &reader, &error) != LSNIF_OK) return fail(error.message);
    lsnif_set_arithmetic(reader, LSNIF_ARITHMETIC_FP32, nullptr);
    std::vector<lsnif_ray> rays(gen.out.size());
    for (std::size_t i = 0; i < rays.size(); ++i) std::memcpy(&rays[i], &gen.out[i].ray, sizeof(lsnif_ray));
    std::vector<lsnif_hit> hits(rays.size());
    const lsnif_status st = lsnif_intersect(reader, rays.data(), rays.size(), hits.data());
    lsnif_close(reader);
    if (st != LSNIF_OK) return fail("lsnif_intersect failed");

    std::string text = "lsnif-conformance 1\n";
    std::vector<float> row(rt.geo.input_width), scratch;
    for (std::size_t i = 0; i < gen.out.size(); ++i) {
        const Ray& r = gen.out[i].ray;
        RayPoints pts;
        const TraceStatus ts = trace_points(rt.geo, asset.occupancy.data(), r, pts);
        std::string voxels = pts.count ? "" : "-";
        for (std::uint32_t k = 0; k < pts.count; ++k) {
            if (k) voxels += ',';
            voxels += std::to_string(pts.voxel[k]);
        }
        std::string logit = "-";
        Hit expected{kInf, {0, 0, 0}, 0, 0};
        if (pts.count) {
            encode_points(rt.geo, grid.data(), pts, row.data());
            const float* o = mlp_forward(rt.net, row.data(), 1, scratch);
            logit = hex(o[OutputLayout::visibility]);
            expected = decode_output(rt.geo, pts, r, o);
        }
        const lsnif_hit& h = hits[i];
        if (h.hit != expected.hit ||
            std::bit_cast<std::uint32_t>(h.t) != std::bit_cast<std::uint32_t>(expected.t))
            return fail("ray " + std::to_string(i) + ": the C API and the fp32 pipeline disagree");
        std::vector<std::string> fields{gen.out[i].name};
        for (const float f : {r.org[0], r.org[1], r.org[2], r.tmin, r.dir[0], r.dir[1], r.dir[2], r.tmax})
            fields.push_back(hex(f));
        fields.insert(fields.end(), {status_name(ts), std::to_string(pts.count), voxels, logit,
                                     std::to_string(h.hit), hex(h.t)});
        for (const float f : h.normal) fields.push_back(hex(f));
        fields.push_back(std::to_string(h.material));
        for (std::size_t k = 0; k < fields.size(); ++k) {
            text += fields[k];
            text += k + 1 < fields.size() ? ' ' : '\n';
        }
    }
    if (const Error e = write_text_atomically(out_path, text)) return fail(out_path + ": " + e.message);
    std::printf("%s: %zu rays\n", out_path.c_str(), gen.out.size());
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    const std::vector<std::string> args(argv + 1, argv + argc);
    if (args.size() == 3 && args[0] == "quantize") return quantize(args[1], args[2]);
    if (args.size() == 2 && args[0] == "synthetic") return synthetic(args[1]);
    if (args.size() == 4 && args[0] == "vectors") return vectors(args[1], args[2], std::stoull(args[3]));
    std::fprintf(stderr,
                 "usage: lsnif_make_conformance quantize IN.lsnif OUT.lsnif\n"
                 "       lsnif_make_conformance synthetic OUT.lsnif\n"
                 "       lsnif_make_conformance vectors ASSET.lsnif OUT.rays SEED\n");
    return 2;
}
