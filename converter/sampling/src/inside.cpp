// The inside test behind family (c)'s rejection sampling and inside_solid(): the 2-bit
// classification grid that settles most points without a ray (cells crossed by no
// surface are wholly inside or outside), and the ray votes for the rest: first-hit facing
// on consistently oriented surfaces (along a short segment to a classified neighbour cell
// first, then random directions), parity of all crossings otherwise, with a majority of
// three when a vote is not clear-cut. Hole caps count as surface here and nowhere else.
// The grid is built once by create(); the votes run concurrently from generate().
#include "sampling_internal.hpp"

namespace lsnif::sampling {

namespace {

// Triangle / axis-aligned box overlap by the separating axis theorem (Akenine-Möller
// 2001, "Fast 3D triangle-box overlap testing"): the box is centred at the origin with
// half extents h, the triangle given relative to that centre. Candidate axes: the box
// normals, the triangle normal and the 9 cross products of edges and box axes. Double
// precision; callers grow h slightly to make it conservative.
bool triangle_box_overlap(const V3 v[3], const double h[3]) {
    const double c[3][3] = {{v[0].x, v[0].y, v[0].z}, {v[1].x, v[1].y, v[1].z}, {v[2].x, v[2].y, v[2].z}};
    for (int a = 0; a < 3; ++a) {
        const double mn = std::min({c[0][a], c[1][a], c[2][a]}), mx = std::max({c[0][a], c[1][a], c[2][a]});
        if (mn > h[a] || mx < -h[a]) return false;
    }
    const V3 e[3] = {v[1] - v[0], v[2] - v[1], v[0] - v[2]};
    auto separated = [&](V3 axis) {
        const double p0 = dot(axis, v[0]), p1 = dot(axis, v[1]), p2 = dot(axis, v[2]);
        const double r = h[0] * std::abs(axis.x) + h[1] * std::abs(axis.y) + h[2] * std::abs(axis.z);
        return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
    };
    if (separated(cross(e[0], e[1]))) return false;
    for (const V3& ed : e)
        for (const V3& u : {V3{1, 0, 0}, V3{0, 1, 0}, V3{0, 0, 1}})
            if (separated(cross(ed, u))) return false;
    return true;
}

// ---- parity counting through an Embree context filter

// RTCIntersectContext must be the first member: the filter receives a pointer to it.
struct ParityContext {
    RTCIntersectContext ctx;
    std::vector<ParityHit>* hits;
};

// Records every candidate hit and rejects it, so one traversal enumerates all crossings
// of the ray. Embree may report a triangle more than once (spatial-split references),
// which odd_crossings() removes.
void parity_filter(const RTCFilterFunctionNArguments* args) {
    auto* pc = reinterpret_cast<ParityContext*>(args->context);
    for (unsigned i = 0; i < args->N; ++i) {
        if (args->valid[i] == 0) continue;
        pc->hits->push_back(
            {RTCRayN_tfar(args->ray, args->N, i), std::uint64_t(RTCHitN_geomID(args->hit, args->N, i)) << 32 |
                                                      RTCHitN_primID(args->hit, args->N, i)});
        args->valid[i] = 0;
    }
}

// Grid cell states while building: kTouched (a triangle overlaps the cell) is also the
// final "vote" state; kUnknown is not yet reached by the flood fill, kVisiting is queued.
constexpr std::uint8_t kTouched = 0, kUnknown = 3, kVisiting = 0xFF;

}  // namespace

// Parity of the number of surface crossings of the ray o + t d, t >= 0. Needs the scene
// flag RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION (set when parity votes are the inside test).
bool EmbreeSource::Impl::odd_crossings(const float o[3], V3 d, std::vector<ParityHit>& hits) const {
    hits.clear();
    ParityContext pc;
    rtcInitIntersectContext(&pc.ctx);
    pc.ctx.filter = parity_filter;
    pc.hits = &hits;
    const float dir[3] = {float(d.x), float(d.y), float(d.z)};
    RTCRayHit rh =
        make_ray_hit(o, dir, 0.0f, INFINITY, kMeshMask | kCapMask);  // caps close the surface for parity
    rtcIntersect1(scene, &pc.ctx, &rh);
    // A triangle is crossed at most once: drop repeated references first.
    std::sort(hits.begin(), hits.end(),
              [](const ParityHit& a, const ParityHit& b) { return a.prim < b.prim; });
    hits.erase(std::unique(hits.begin(), hits.end(),
                           [](const ParityHit& a, const ParityHit& b) { return a.prim == b.prim; }),
               hits.end());
    // The crossings' distances computed by lsnif (exact_hit): Embree's carry the CPU's
    // approximate reciprocal, and the tolerance below compares them.
    const format::Ray ray{{o[0], o[1], o[2]}, 0.0f, {dir[0], dir[1], dir[2]}, INFINITY};
    for (ParityHit& h : hits) {
        const RawHit embree{h.t, 0.0f, 0.0f, std::uint32_t(h.prim & 0xFFFFFFFFu)};
        h.t = exact_hit(ray, embree, unsigned(h.prim >> 32)).t;
    }
    // A ray through a shared edge or vertex is reported by every triangle there:
    // crossings closer than 1e-6 x diagonal count once.
    std::sort(hits.begin(), hits.end(), [](const ParityHit& a, const ParityHit& b) { return a.t < b.t; });
    const double tol = 1e-6 * diag;
    std::size_t crossings = 0;
    double last = -INFINITY;
    for (const ParityHit& h : hits) {
        if (double(h.t) - last > tol) ++crossings;
        last = h.t;
    }
    return (crossings & 1) != 0;
}

// For a closed, consistently oriented surface: o is inside iff the first surface the
// ray o + t d meets faces away from it (the ray leaves the solid there). One
// closest-hit query, which stops at that first hit; origins that need a vote lie in
// grid cells the surface crosses, so the hit is usually close. `clean` is false when
// the answer could be an artefact of float precision: the hit is within 1e-6 of a
// triangle edge (barycentrics), grazing (|cos| < 1e-3) or at the origin.
// With a finite `tfar`, `missed` reports that nothing was hit before it (then the
// result is false and clean).
bool EmbreeSource::Impl::first_hit_from_inside(const float o[3], V3 d, bool& clean, float tfar,
                                               bool* missed) const {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    const float dir[3] = {float(d.x), float(d.y), float(d.z)};
    RTCRayHit rh = make_ray_hit(o, dir, 0.0f, tfar, kMeshMask | kCapMask);
    rtcIntersect1(scene, &ctx, &rh);
    clean = true;
    if (missed) *missed = rh.hit.geomID == RTC_INVALID_GEOMETRY_ID;
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
    // Embree's unnormalized geometric normal follows the same right-hand rule on
    // (v0, v1, v2) as the records (mesh and caps alike), and reading it avoids a
    // cache miss on a per-triangle record. Zero (degenerate): cosine 0, not clean.
    const V3 ng{rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z};
    const double len = length(ng);
    const double cosine = len > 0 ? orientation * dot(d, ng) / len : 0.0;
    // The hit's t, u and v computed by lsnif (exact_hit: Embree's carry the CPU's approximate
    // reciprocal), on a mesh triangle or a hole cap.
    const RawHit h = exact_hit(format::Ray{{o[0], o[1], o[2]}, 0.0f, {dir[0], dir[1], dir[2]}, tfar},
                               RawHit{rh.ray.tfar, rh.hit.u, rh.hit.v, rh.hit.primID}, rh.hit.geomID);
    const double u = h.u, v = h.v;
    clean = std::abs(cosine) >= 1e-3 && std::min({u, v, 1.0 - u - v}) >= 1e-6 && h.t > 1e-7 * diag;
    return cosine > 0;
}

// One vote along direction d: first-hit facing when the surface is oriented, else parity
// (never `clean`: a parity vote always takes part in a majority).
bool EmbreeSource::Impl::vote(const float o[3], V3 d, std::vector<ParityHit>& hits, bool& clean) const {
    if (oriented) return first_hit_from_inside(o, d, clean);
    clean = false;
    return odd_crossings(o, d, hits);
}

// First-hit votes: one clean vote decides. Otherwise (parity votes, or an unclean
// first-hit vote) the majority of three votes along random directions, the third only
// when the first two disagree. A vote goes wrong only when its ray grazes an edge or
// vertex within float precision; two independent directions doing so is negligible.
// `queries` counts the rays traced; rng supplies the directions (the vote stream).
bool EmbreeSource::Impl::parity_inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits,
                                       std::uint64_t& queries) const {
    bool clean = false;
    if (oriented && !packed_grid.empty()) {
        const bool a = segment_vote(o, clean, queries);
        if (clean) return a;
    }
    const bool a = vote(o, uniform_sphere(rng), hits, clean);
    ++queries;
    if (clean) return a;
    const bool b = vote(o, uniform_sphere(rng), hits, clean);
    ++queries;
    if (a == b) return a;
    ++queries;
    return vote(o, uniform_sphere(rng), hits, clean);
}

// First-hit vote along the segment from o to the centre of a classified cell next to
// o's cell (closed, consistently oriented surfaces with a classification grid).
// Untouched cells lie wholly on one side of the surface (build_grid()), so if the
// segment meets no surface, o has that cell's state; otherwise the facing of the first
// hit decides, as in any first-hit vote. A segment of at most 1.5 cells is a much
// cheaper traversal than a ray in a random direction, which from a point next to the
// surface often runs across the whole model.
// `clean` false: no classified face neighbour, or the hit is not clean (the caller
// falls back to random directions).
bool EmbreeSource::Impl::segment_vote(const float o[3], bool& clean, std::uint64_t& queries) const {
    clean = false;
    std::size_t g[3];
    for (int a = 0; a < 3; ++a) {
        const double t = (double(o[a]) - lo[a]) * inv_cell[a];
        g[a] = std::size_t(std::max(0.0, std::min(t, double(grid_res - 1))));
    }
    // The classified face neighbour whose centre is nearest to o.
    double best = INFINITY;
    V3 target{};
    unsigned target_state = 0;
    for (int a = 0; a < 3; ++a)
        for (int step : {-1, 1}) {
            if ((step < 0 && g[a] == 0) || (step > 0 && g[a] + 1 >= grid_res)) continue;
            std::size_t q[3] = {g[0], g[1], g[2]};
            q[a] = step < 0 ? q[a] - 1 : q[a] + 1;
            const unsigned state = cell_state(q[0] + grid_res * (q[1] + grid_res * q[2]));
            if (!state) continue;
            const V3 ctr{lo[0] + (double(q[0]) + 0.5) / inv_cell[0],
                         lo[1] + (double(q[1]) + 0.5) / inv_cell[1],
                         lo[2] + (double(q[2]) + 0.5) / inv_cell[2]};
            const V3 d = ctr - V3{o[0], o[1], o[2]};
            const double d2 = dot(d, d);
            if (d2 < best) best = d2, target = ctr, target_state = state;
        }
    if (!target_state || !(best > 0)) return false;
    const V3 d = target - V3{o[0], o[1], o[2]};
    const double len = std::sqrt(best);
    bool missed = false;
    ++queries;
    const bool in = first_hit_from_inside(o, (1.0 / len) * d, clean, float(len), &missed);
    return missed ? target_state == 2 : in;
}

// The whole inside test for one point: the grid when it decides, votes otherwise.
bool EmbreeSource::Impl::inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits,
                                std::uint64_t& queries) const {
    if (!packed_grid.empty()) {
        const unsigned state = cell_state(cell_of(o));
        if (state) return state == 2;
    }
    return parity_inside(o, rng, hits, queries);
}

// Marks every cell a triangle (mesh or hole cap) overlaps (separating-axis test on the
// cell grown by 1e-3 of its size: conservative against rounding), then classifies the
// untouched cells (classify_untouched_cells()). Input: grid_res = cfg.classify_resolution
// > 0, the construction copies of the mesh and the caps, the committed scene (votes).
void EmbreeSource::Impl::build_grid() {
    const std::uint32_t R = cfg.classify_resolution;
    grid_res = R;
    for (int a = 0; a < 3; ++a) inv_cell[a] = double(R) / (hi[a] - lo[a]);
    grid.assign(std::size_t(R) * R * R, kUnknown);
    mark_touched_cells();
    classify_untouched_cells();
}

// Sets grid[cell] = kTouched for every cell a triangle of the mesh or the caps overlaps.
void EmbreeSource::Impl::mark_touched_cells() {
    const std::uint32_t R = grid_res;
    // Cells grown by 1e-3 of their size on every side: conservative against rounding in
    // the overlap test and in cell_of().
    double size[3], half[3];
    for (int a = 0; a < 3; ++a) {
        size[a] = (hi[a] - lo[a]) / double(R);
        half[a] = 0.5 * size[a] * (1.0 + 2e-3);
    }
    const std::size_t all = triangles + caps.size() / 3;
    for (std::size_t t = 0; t < all; ++t) {
        const std::uint32_t* tri = t < triangles ? &indices[3 * t] : &caps[3 * (t - triangles)];
        std::size_t k0[3], k1[3];  // the triangle's bounding box in cells, grown the same way
        for (int a = 0; a < 3; ++a) {
            double mn = INFINITY, mx = -INFINITY;
            for (int j = 0; j < 3; ++j) {
                const double p = positions[3 * std::size_t(tri[j]) + std::size_t(a)];
                mn = std::min(mn, p);
                mx = std::max(mx, p);
            }
            const double g0 = std::floor((mn - lo[a]) * inv_cell[a] - 1e-3);
            const double g1 = std::floor((mx - lo[a]) * inv_cell[a] + 1e-3);
            k0[a] = std::size_t(std::clamp(g0, 0.0, double(R - 1)));
            k1[a] = std::size_t(std::clamp(g1, 0.0, double(R - 1)));
        }
        const V3 p[3] = {vertex(tri[0]), vertex(tri[1]), vertex(tri[2])};
        for (std::size_t z = k0[2]; z <= k1[2]; ++z)
            for (std::size_t y = k0[1]; y <= k1[1]; ++y)
                for (std::size_t x = k0[0]; x <= k1[0]; ++x) {
                    const std::size_t cell = x + R * (y + R * z);
                    if (grid[cell] == kTouched) continue;
                    const V3 ctr{lo[0] + (double(x) + 0.5) * size[0], lo[1] + (double(y) + 0.5) * size[1],
                                 lo[2] + (double(z) + 0.5) * size[2]};
                    const V3 rel[3] = {p[0] - ctr, p[1] - ctr, p[2] - ctr};
                    if (triangle_box_overlap(rel, half)) grid[cell] = kTouched;
                }
    }
}

// Labels the untouched cells by 6-connected components (flood fill). No surface passes
// through an untouched cell, so a component is wholly inside or wholly outside; one that
// touches the box's faces is outside (the box contains the mesh); any other is decided by
// the majority of inside votes at up to three of its cell centres (a fixed stream, so the
// grid is a function of the mesh alone). Output: grid cells 1 (outside) or 2 (inside).
void EmbreeSource::Impl::classify_untouched_cells() {
    const std::uint32_t R = grid_res;
    const std::size_t cells = grid.size();
    std::vector<std::size_t> stack, members;
    Rng rng{mix64(0x636C6173736966ull)};
    std::vector<ParityHit> hits;
    std::uint64_t queries = 0;
    auto flood = [&](std::size_t start, std::vector<std::size_t>& out) {
        out.clear();
        stack.assign(1, start);
        grid[start] = kVisiting;
        while (!stack.empty()) {
            const std::size_t c = stack.back();
            stack.pop_back();
            out.push_back(c);
            const std::size_t x = c % R, y = (c / R) % R, z = c / (std::size_t(R) * R);
            const std::size_t nb[6][3] = {{x - 1, y, z}, {x + 1, y, z}, {x, y - 1, z},
                                          {x, y + 1, z}, {x, y, z - 1}, {x, y, z + 1}};
            for (const auto& q : nb) {
                if (q[0] >= R || q[1] >= R || q[2] >= R) continue;  // wraps below 0 too
                const std::size_t n = q[0] + R * (q[1] + R * q[2]);
                if (grid[n] == kUnknown) {
                    grid[n] = kVisiting;
                    stack.push_back(n);
                }
            }
        }
    };
    auto on_border = [&](std::size_t m) {
        const std::size_t x = m % R, y = (m / R) % R, z = m / (std::size_t(R) * R);
        return x == 0 || y == 0 || z == 0 || x == R - 1 || y == R - 1 || z == R - 1;
    };
    for (std::size_t c = 0; c < cells; ++c) {
        if (grid[c] != kUnknown) continue;
        flood(c, members);
        std::uint8_t state = 1;
        if (std::none_of(members.begin(), members.end(), on_border)) {
            int inside_votes = 0, votes = 0;
            for (std::size_t k = 0; k < std::min<std::size_t>(3, members.size()); ++k) {
                const std::size_t m = members[k * members.size() / 3];
                const std::size_t idx[3] = {m % R, (m / R) % R, m / (std::size_t(R) * R)};
                float o[3];
                for (int a = 0; a < 3; ++a) o[a] = float(lo[a] + (double(idx[a]) + 0.5) / inv_cell[a]);
                inside_votes += parity_inside(o, rng, hits, queries) ? 1 : 0;
                ++votes;
            }
            state = 2 * inside_votes > votes ? 2 : 1;
        }
        for (std::size_t m : members) grid[m] = state;
    }
}

void build_classification_grid(EmbreeSource::Impl& m) {
    FastFloatScope ffs;  // the votes trace rays, under the same float mode as generate()
    m.build_grid();
    m.packed_grid.assign((m.grid.size() + 3) / 4, 0);
    for (std::size_t c = 0; c < m.grid.size(); ++c)
        m.packed_grid[c >> 2] = std::uint8_t(m.packed_grid[c >> 2] | (m.grid[c] & 3u) << (2 * (c & 3)));
}

bool EmbreeSource::inside_solid(const std::array<float, 3>& p, std::uint64_t seed) const {
    if (!rejects_interior()) return false;  // open mesh: no votes (its scene is not built for them)
    Rng rng = ray_rng(seed, 0xFFFFFFFFFFFFFFFFull);
    std::vector<ParityHit> hits;
    std::uint64_t queries = 0;
    FastFloatScope ffs;
    return impl_->inside(p.data(), rng, hits, queries);
}

}  // namespace lsnif::sampling
