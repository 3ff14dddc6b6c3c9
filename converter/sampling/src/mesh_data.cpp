// The mesh as the samplers store it: the construction stages that copy the validated
// input, derive per-triangle geometry (unit geometric normals, areas), build the alias
// table that picks family (b)'s triangles in proportion to area (Vose 1991), pack all of
// it into the two cache-line records per triangle that generation reads, and finally drop
// the construction copies. Kept apart from the Embree scene and the topology analysis,
// which read the same copies but answer different questions.
#include "sampling_internal.hpp"

namespace lsnif::sampling {

void copy_input(EmbreeSource::Impl& m, const MeshView& mesh, const Box& box, const SamplingConfig& cfg) {
    m.cfg = cfg;
    m.positions.assign(mesh.positions.begin(), mesh.positions.end());
    m.indices.assign(mesh.indices.begin(), mesh.indices.end());
    m.normals.assign(mesh.normals.begin(), mesh.normals.end());
    m.materials.assign(mesh.materials.begin(), mesh.materials.end());
    m.triangles = mesh.indices.size() / 3;
    double d2 = 0;
    for (int a = 0; a < 3; ++a) {
        m.lo[a] = box.min[std::size_t(a)];
        m.hi[a] = box.max[std::size_t(a)];
        m.center[a] = 0.5 * (m.lo[a] + m.hi[a]);
        d2 += (m.hi[a] - m.lo[a]) * (m.hi[a] - m.lo[a]);
    }
    m.diag = std::sqrt(d2);
}

TriangleAreas compute_face_geometry(EmbreeSource::Impl& m) {
    const std::size_t nt = m.triangles;
    m.face_normals.assign(3 * nt, 0.0f);
    TriangleAreas out;
    out.area.resize(nt);
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t* v = &m.indices[3 * t];
        const V3 c = cross(m.vertex(v[1]) - m.vertex(v[0]), m.vertex(v[2]) - m.vertex(v[0]));
        const double len = length(c);
        out.area[t] = 0.5 * len;
        out.total += out.area[t];
        if (len > 0) {
            m.face_normals[3 * t] = float(c.x / len);
            m.face_normals[3 * t + 1] = float(c.y / len);
            m.face_normals[3 * t + 2] = float(c.z / len);
        }
    }
    return out;
}

void build_alias_table(EmbreeSource::Impl& m, const TriangleAreas& areas) {
    const std::size_t nt = m.triangles;
    const std::vector<double>& area = areas.area;
    m.alias_prob.assign(nt, 1.0);
    m.alias_index.resize(nt);
    std::vector<double> scaled(nt);
    std::vector<std::uint32_t> small, large;
    for (std::size_t t = 0; t < nt; ++t) {
        m.alias_index[t] = std::uint32_t(t);
        scaled[t] = area[t] * double(nt) / areas.total;
        (scaled[t] < 1.0 ? small : large).push_back(std::uint32_t(t));
    }
    while (!small.empty() && !large.empty()) {
        const std::uint32_t l = small.back(), g = large.back();
        small.pop_back();
        m.alias_prob[l] = scaled[l];
        m.alias_index[l] = g;
        scaled[g] = (scaled[g] + scaled[l]) - 1.0;
        if (scaled[g] < 1.0) {
            large.pop_back();
            small.push_back(g);
        }
    }
    // Leftovers (rounding) keep probability 1 and alias themselves; a zero-area
    // leftover would be chosen, so give it away to the largest triangle instead.
    const std::uint32_t biggest = std::uint32_t(std::max_element(area.begin(), area.end()) - area.begin());
    for (std::uint32_t l : small)
        if (area[l] == 0) {
            m.alias_prob[l] = 0.0;
            m.alias_index[l] = biggest;
        }
}

namespace {

// The triangle of vertex indices v as a corner and two edges (edges in double, rounded once).
void corner_and_edges(const EmbreeSource::Impl& m, const std::uint32_t* v, float v0[3], float e1[3],
                      float e2[3]) {
    const V3 p0 = m.vertex(v[0]), d1 = m.vertex(v[1]) - p0, d2 = m.vertex(v[2]) - p0;
    const double ev[2][3] = {{d1.x, d1.y, d1.z}, {d2.x, d2.y, d2.z}};
    for (int a = 0; a < 3; ++a) {
        v0[a] = m.positions[3 * std::size_t(v[0]) + std::size_t(a)];
        e1[a] = float(ev[0][a]);
        e2[a] = float(ev[1][a]);
    }
}

}  // namespace

void build_triangle_records(EmbreeSource::Impl& m) {
    const std::size_t nt = m.triangles;
    m.surface.resize(nt);
    m.hit_records.resize(nt);
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t* v = &m.indices[3 * t];
        EmbreeSource::Impl::SurfaceRecord& sr = m.surface[t];
        EmbreeSource::Impl::HitRecord& hr = m.hit_records[t];
        corner_and_edges(m, v, sr.v0, sr.e1, sr.e2);
        for (int a = 0; a < 3; ++a) {
            sr.ng[a] = hr.ng[a] = m.face_normals[3 * t + std::size_t(a)];
            for (int j = 0; j < 3; ++j) hr.n[j][a] = m.normals[3 * std::size_t(v[j]) + std::size_t(a)];
        }
        sr.keep = float(m.alias_prob[t]);
        sr.alias = m.alias_index[t];
        hr.material = m.materials.empty() ? 0 : m.materials[t];
        for (int j = 0; j < 3; ++j) hr.corner[j] = v[j];
    }
    m.around = base::VertexTriangles(m.indices, m.positions.size() / 3);
    m.tie_margin = base::tie_margin(m.lo, m.hi);
    m.cap_records.resize(m.caps.size() / 3);
    for (std::size_t k = 0; k < m.cap_records.size(); ++k) {
        EmbreeSource::Impl::CapRecord& c = m.cap_records[k];
        corner_and_edges(m, &m.caps[3 * k], c.v0, c.e1, c.e2);
    }
}

void release_construction_data(EmbreeSource::Impl& m) {
    for (auto* v : {&m.positions, &m.normals, &m.face_normals}) std::vector<float>().swap(*v);
    for (auto* v : {&m.indices, &m.materials, &m.alias_index}) std::vector<std::uint32_t>().swap(*v);
    std::vector<double>().swap(m.alias_prob);
    std::vector<std::uint8_t>().swap(m.grid);
}

}  // namespace lsnif::sampling
