// Edge topology of the mesh, which decides whether family (c) can reject origins inside
// the solid and how the inside test votes: positions are welded by exact value, edges
// counted, the mesh classified as closed / closed mod 2 / open and as consistently
// oriented or not, small holes capped with triangle fans (so scans and CAD exports that
// miss a few triangles still have an inside), and the orientation's sign taken from the
// signed volume. Construction only: everything here runs once inside create(), before
// the Embree scene (which needs the caps) is built.
#include "sampling_internal.hpp"

#include <cstring>
#include <unordered_map>
#include <utility>

namespace lsnif::sampling {

namespace {

using Edge = std::pair<std::uint32_t, std::uint32_t>;

// Canonical vertex id per vertex: the first vertex with bit-identical coordinates (-0 and
// +0 are the same). Exported meshes often split vertices at normal or UV seams; welding
// makes those seams shared edges again.
std::vector<std::uint32_t> weld_positions(const std::vector<float>& positions) {
    const std::size_t nv = positions.size() / 3;
    std::unordered_map<std::uint64_t, std::vector<std::uint32_t>> buckets;  // hash -> canonical ids
    std::vector<std::uint32_t> canon(nv);
    auto bits = [](float f) {
        f += 0.0f;  // -0 -> +0
        std::uint32_t b;
        std::memcpy(&b, &f, 4);
        return b;
    };
    buckets.reserve(nv);
    for (std::size_t i = 0; i < nv; ++i) {
        const std::uint32_t bx = bits(positions[3 * i]), by = bits(positions[3 * i + 1]),
                            bz = bits(positions[3 * i + 2]);
        const std::uint64_t h = mix64((std::uint64_t(bx) << 32 | by) ^ mix64(bz));
        auto& list = buckets[h];
        std::uint32_t id = std::uint32_t(i);
        for (std::uint32_t j : list)
            if (bits(positions[3 * std::size_t(j)]) == bx && bits(positions[3 * std::size_t(j) + 1]) == by &&
                bits(positions[3 * std::size_t(j) + 2]) == bz) {
                id = j;
                break;
            }
        if (id == i) list.push_back(id);
        canon[i] = id;
    }
    return canon;
}

// Half-edges a -> b of the non-degenerate triangles (welded ids) as
// (min << 32 | max) << 1 | (a > b), sorted, so the uses of one undirected edge are adjacent.
std::vector<std::uint64_t> sorted_half_edges(const std::vector<std::uint32_t>& indices,
                                             const std::vector<std::uint32_t>& canon) {
    const std::size_t nt = indices.size() / 3;
    std::vector<std::uint64_t> edges;
    edges.reserve(3 * nt);
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t a = canon[indices[3 * t]], b = canon[indices[3 * t + 1]],
                            c = canon[indices[3 * t + 2]];
        if (a == b || b == c || c == a) continue;  // degenerate: no edges of its own
        for (auto [p, q] : {std::pair{a, b}, std::pair{b, c}, std::pair{c, a}})
            edges.push_back((std::uint64_t(std::min(p, q)) << 32 | std::max(p, q)) << 1 | (p > q ? 1u : 0u));
    }
    std::sort(edges.begin(), edges.end());
    return edges;
}

struct EdgeSummary {
    bool closed = false;    // every edge used exactly twice
    bool oriented = false;  // every edge used once, or twice in opposite directions
    // Edges used an odd number of times, as directed edges for the caps: the reverse of
    // the single half-edge when the surface is oriented.
    std::vector<Edge> odd;
};

EdgeSummary summarize_edges(const std::vector<std::uint64_t>& edges) {
    EdgeSummary s;
    s.closed = s.oriented = !edges.empty();
    for (std::size_t i = 0; i < edges.size();) {
        std::size_t j = i, forward = 0;
        while (j < edges.size() && (edges[j] >> 1) == (edges[i] >> 1)) forward += !(edges[j++] & 1);
        const std::size_t n = j - i;
        const std::uint32_t lo_v = std::uint32_t(edges[i] >> 33), hi_v = std::uint32_t(edges[i] >> 1);
        s.closed = s.closed && n == 2;
        s.oriented = s.oriented && ((n == 2 && forward == 1) || n == 1);
        if (n & 1) s.odd.push_back(forward ? std::pair{hi_v, lo_v} : std::pair{lo_v, hi_v});
        i = j;
    }
    return s;
}

// Splits the odd edges into simple cycles (walk until a vertex repeats, emit the repeated
// part) and fans each one into m.caps. With `directed`, edges are only walked from first
// to second (the caps then continue the mesh's orientation); every vertex has as many
// outgoing as incoming odd edges, so the walks close. Returns false (and leaves no caps)
// when a loop's bounding-box diagonal exceeds `max_extent`: that mesh is genuinely open.
bool cap_holes(EmbreeSource::Impl& m, const std::vector<Edge>& odd, bool directed, double max_extent) {
    std::unordered_map<std::uint32_t, std::vector<std::size_t>> at;  // vertex -> walkable edges
    for (std::size_t e = 0; e < odd.size(); ++e) {
        at[odd[e].first].push_back(e);
        if (!directed) at[odd[e].second].push_back(e);
    }
    std::vector<char> used(odd.size(), 0);
    std::vector<std::uint32_t> caps, path;
    std::unordered_map<std::uint32_t, std::size_t> on_path;
    bool small = true;
    auto emit = [&](std::size_t from) {  // path[from..] is a simple cycle
        double lo3[3] = {INFINITY, INFINITY, INFINITY}, hi3[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (std::size_t k = from; k < path.size(); ++k)
            for (int a = 0; a < 3; ++a) {
                lo3[a] = std::min(lo3[a], double(m.positions[3 * std::size_t(path[k]) + std::size_t(a)]));
                hi3[a] = std::max(hi3[a], double(m.positions[3 * std::size_t(path[k]) + std::size_t(a)]));
            }
        const double ext = length(V3{hi3[0] - lo3[0], hi3[1] - lo3[1], hi3[2] - lo3[2]});
        if (!(ext <= max_extent)) small = false;
        for (std::size_t k = from + 1; k + 1 < path.size(); ++k)
            caps.insert(caps.end(), {path[from], path[k], path[k + 1]});
    };
    for (std::size_t start = 0; start < odd.size() && small; ++start) {
        if (used[start]) continue;
        path.assign(1, odd[start].first);
        on_path.clear();
        on_path[path[0]] = 0;
        std::uint32_t cur = path[0];
        for (;;) {
            std::size_t next = odd.size();
            for (std::size_t e : at[cur])
                if (!used[e]) {
                    next = e;
                    break;
                }
            if (next == odd.size()) break;  // only back at the walk's start (balanced degrees)
            used[next] = 1;
            cur = odd[next].first == cur ? odd[next].second : odd[next].first;
            if (auto it = on_path.find(cur); it != on_path.end()) {
                const std::size_t j = it->second;
                emit(j);
                for (std::size_t k = j + 1; k < path.size(); ++k) on_path.erase(path[k]);
                path.resize(j + 1);
            } else {
                on_path[cur] = path.size();
                path.push_back(cur);
            }
        }
    }
    if (!small) return false;
    m.caps = std::move(caps);
    return true;
}

// Signed volume (about the box centre, divergence theorem) of the mesh and its caps, which
// says whether a consistent orientation points out of or into the solid. Sets m.oriented
// (false when the volume is zero or not finite: no usable facing) and m.orientation.
void orient_solid(EmbreeSource::Impl& m) {
    const V3 ctr{m.center[0], m.center[1], m.center[2]};
    double volume = 0;
    auto add = [&](const std::uint32_t* v) {
        volume += dot(m.vertex(v[0]) - ctr, cross(m.vertex(v[1]) - ctr, m.vertex(v[2]) - ctr));
    };
    for (std::size_t t = 0; t < m.triangles; ++t) add(&m.indices[3 * t]);
    for (std::size_t t = 0; t < m.caps.size(); t += 3) add(&m.caps[t]);
    m.oriented = volume != 0 && std::isfinite(volume);
    m.orientation = volume < 0 ? -1.0 : 1.0;
}

}  // namespace

void analyze_topology(EmbreeSource::Impl& m) {
    const std::vector<std::uint64_t> edges = sorted_half_edges(m.indices, weld_positions(m.positions));
    const EdgeSummary s = summarize_edges(edges);
    m.closed = s.closed;
    // Parity is well defined iff every edge is used an even number of times (the
    // surface is a mod-2 cycle). Otherwise the odd edges form closed loops (every
    // vertex has even degree among them); when every loop is small, a fan over it
    // closes the surface for the inside test (Embree geometry 1, invisible to
    // ground-truth rays through the ray mask). Loops of an oriented surface are walked
    // against its boundary half-edges, so the caps continue the orientation.
    if (s.odd.empty()) {
        m.parity_ready = !edges.empty();
    } else if (m.cfg.max_hole_size > 0) {
        m.parity_ready = cap_holes(m, s.odd, s.oriented, double(m.cfg.max_hole_size) * m.diag);
    }
    if (m.parity_ready && s.oriented) orient_solid(m);
}

}  // namespace lsnif::sampling
