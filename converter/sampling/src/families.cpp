// The three ray families and their ground truth: how generate() builds rays in batches
// (draw / resolve / finish passes that prefetch the random table lookups a pass ahead),
// the per-family constructions (outside sphere, surface-leaving, interior with rejection
// through the inside test), tracing 16 rays at a time through rtcIntersect16, and trace()
// for caller-made rays through rtcIntersect1. Both tracing paths decode hits with the
// same code, which is why they must round identically (-ffp-contract=off) and why the
// tests can compare them bit for bit. A hit's t, u and v are lsnif's own (exact_hit):
// Embree only says which triangle, and where several meet the ray at one point lsnif
// chooses (tied_hit).
#include "sampling_internal.hpp"

#include <algorithm>
#include <bit>
#include <cmath>

namespace lsnif::sampling {

using samples::Family;
using samples::Sample;

namespace {

// Orthonormal frame around unit n (Duff et al. 2017, "Building an orthonormal basis,
// revisited"); returns x*t + y*b + z*n.
V3 from_frame(V3 n, double x, double y, double z) {
    const double sign = std::copysign(1.0, n.z);
    const double a = -1.0 / (sign + n.z), b = n.x * n.y * a;
    const V3 t{1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x};
    const V3 bt{b, sign + n.y * n.y * a, -n.y};
    return x * t + y * bt + z * n;
}

// Direction over the hemisphere around unit n, cosine-weighted (`cosine`) or uniform,
// from one uniform disk point (x, y), q = x^2 + y^2, lifted in n's frame:
//   cosine-weighted  (x, y, sqrt(1-q))              (Malley's method, PBRT 3rd ed. §13.6.3)
//   uniform          (2x sqrt(1-q), 2y sqrt(1-q), |1-2q|)
// The second is Marsaglia's sphere point with its height folded onto n's side: 1-2q is
// uniform in (-1, 1), so |1-2q| is uniform in [0, 1), which is the uniform hemisphere.
// Both laws share the disk point and the frame, and the law is chosen by selects, not
// branches (the law is a coin flip, which no branch predictor learns).
V3 hemisphere(Rng& rng, V3 n, bool cosine) {
    double x, y, q;
    unit_disk(rng, x, y, q);
    const double r = std::sqrt(1.0 - q), f = cosine ? 1.0 : 2.0 * r;
    return from_frame(n, f * x, f * y, cosine ? r : std::abs(1.0 - 2.0 * q));
}

// The origin as it will be stored (float): the inside test and the sample see the same point.
void store_origin(V3 o, float of[3]) {
    of[0] = float(o.x), of[1] = float(o.y), of[2] = float(o.z);
}

}  // namespace

// ---- ground truth

// Traces r against the mesh (not the hole caps). Invalid rays (non-finite, zero
// direction, tmin < 0 or > tmax) report a miss without calling Embree.
EmbreeSource::Impl::RawHit EmbreeSource::Impl::trace_raw(const format::Ray& r) const {
    RawHit out{0, 0, 0, kNoPrimitive};
    bool valid = std::isfinite(r.tmin) && r.tmin >= 0 && !(r.tmax < r.tmin) && !std::isnan(r.tmax);
    for (int i = 0; i < 3; ++i) valid = valid && std::isfinite(r.org[i]) && std::isfinite(r.dir[i]);
    valid = valid && (r.dir[0] != 0 || r.dir[1] != 0 || r.dir[2] != 0);
    if (!valid) return out;
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    RTCRayHit rh =
        make_ray_hit(r.org, r.dir, r.tmin, r.tmax, kMeshMask);  // the mesh only, never the hole caps
    rtcIntersect1(scene, &ctx, &rh);
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return out;
    return {rh.ray.tfar, rh.hit.u, rh.hit.v, rh.hit.primID};
}

namespace {

// Ray r's hit with triangle h.prim (one Embree reported) computed again from the
// triangle's stored corner and edges (base::triangle_hit: the same bits on every CPU, where
// Embree's t, u and v are the CPU's own; docs/pipeline.md "The same bytes everywhere"), so
// the ground truth takes only the triangle from Embree. t stays within the ray's [tmin,
// tmax], which Embree's exact depth test guaranteed. Embree's values are kept where
// triangle_hit has none.
template <class Triangle>
EmbreeSource::Impl::RawHit moeller_trumbore(const Triangle& tri, const format::Ray& r,
                                            const EmbreeSource::Impl::RawHit& h) {
    base::TriangleHit x;
    if (!base::triangle_hit(V3{r.org[0], r.org[1], r.org[2]}, V3{r.dir[0], r.dir[1], r.dir[2]},
                            V3{tri.v0[0], tri.v0[1], tri.v0[2]}, V3{tri.e1[0], tri.e1[1], tri.e1[2]},
                            V3{tri.e2[0], tri.e2[1], tri.e2[2]}, x))
        return h;
    return {std::clamp(float(x.t), r.tmin, r.tmax), float(x.u), float(x.v), h.prim};
}

}  // namespace

EmbreeSource::Impl::RawHit EmbreeSource::Impl::exact_hit(const format::Ray& r, const RawHit& h) const {
    return moeller_trumbore(surface[h.prim], r, h);
}

// Ray r's hit with triangle h.prim, and which triangle it is on where several meet the ray at
// one point: base::exact_tied_hit among the triangles around h.prim's corners. Embree puts
// first whichever its approximate distances say, whose bits are the CPU's (and its
// kernel's), and a training target with other normal bits sends training elsewhere
// (docs/pipeline.md "The same bytes everywhere"). Hits clear of the border are exact_hit's.
EmbreeSource::Impl::RawHit EmbreeSource::Impl::tied_hit(const format::Ray& r, const RawHit& h) const {
    const auto triangle = [this](std::uint32_t c, V3& v0, V3& e1, V3& e2) {
        const SurfaceRecord& s = surface[c];
        v0 = {s.v0[0], s.v0[1], s.v0[2]};
        e1 = {s.e1[0], s.e1[1], s.e1[2]};
        e2 = {s.e2[0], s.e2[1], s.e2[2]};
    };
    const V3 org{r.org[0], r.org[1], r.org[2]}, dir{r.dir[0], r.dir[1], r.dir[2]};
    const std::optional<base::ChosenHit> chosen = base::exact_tied_hit(
        org, dir, r.tmin, r.tmax, tie_margin, h.prim, hit_records[h.prim].corner, around, triangle);
    if (!chosen) return h;
    const base::TriangleHit& x = chosen->hit;
    return {std::clamp(float(x.t), r.tmin, r.tmax), float(x.u), float(x.v), chosen->triangle};
}

// The same for a hit on either geometry of the inside test's rays: the mesh's triangles or
// the hole caps'.
EmbreeSource::Impl::RawHit EmbreeSource::Impl::exact_hit(const format::Ray& r, const RawHit& h,
                                                         unsigned geometry) const {
    return geometry == kCapGeometry ? moeller_trumbore(cap_records[h.prim], r, h) : exact_hit(r, h);
}

// The two cache lines decode() reads for a hit on triangle `prim`: its vertices
// (exact_hit) and its normals.
void EmbreeSource::Impl::prefetch_hit(std::uint32_t prim) const {
    __builtin_prefetch(&surface[prim]);
    __builtin_prefetch(&hit_records[prim]);
}

// Writes the ground-truth fields of s (and x) from Embree's answer.
void EmbreeSource::Impl::decode(const RawHit& embree, Sample& s, SampleExtras* x) const {
    // Hits and misses take the same path (a miss reads record 0 and its results are
    // replaced by zeros): whether a ray hits is a coin flip to the branch predictor.
    const bool hit = embree.prim != kNoPrimitive;
    const RawHit h = hit ? tied_hit(s.ray, embree) : embree;
    const HitRecord& rec = hit_records[hit ? h.prim : 0];
    // Embree's (u, v) are the barycentrics of v1 and v2: P = (1-u-v) v0 + u v1 + v v2.
    const float u = hit ? h.u : 0.0f, v = hit ? h.v : 0.0f, w = 1.0f - u - v;
    float n[3], len2 = 0;
    for (int i = 0; i < 3; ++i) {
        n[i] = w * rec.n[0][i] + u * rec.n[1][i] + v * rec.n[2][i];
        len2 += n[i] * n[i];
    }
    if (len2 > 1e-20f && std::isfinite(len2)) {
        const float inv = 1.0f / std::sqrt(len2);
        for (int i = 0; i < 3; ++i) n[i] *= inv;
    } else {  // opposite vertex normals cancel: fall back to the faceted normal
        for (int i = 0; i < 3; ++i) n[i] = rec.ng[i];
    }
    for (int i = 0; i < 3; ++i) s.normal[i] = hit ? n[i] : 0.0f;
    s.t = hit ? h.t : 0.0f;
    s.material = hit ? rec.material : 0;
    s.hit = hit ? 1 : 0;
    if (x) {
        for (int i = 0; i < 3; ++i) x->geometric_normal[std::size_t(i)] = hit ? rec.ng[i] : 0.0f;
        x->primitive = h.prim;
    }
}

// Ground truth for samples [b, e) whose rays are set: all traces first (each issuing a
// prefetch of the hit triangle's records), then all decodes, so the record loads
// overlap the following traversals instead of stalling after each one.
void EmbreeSource::Impl::trace_range(Sample* s, SampleExtras* x, std::size_t n) const {
    RawHit raw[kBatch];
    for (std::size_t b = 0; b < n; b += kBatch) {
        const std::size_t m = std::min(kBatch, n - b);
        for (std::size_t i = 0; i < m; ++i) {
            raw[i] = trace_raw(s[b + i].ray);
            if (raw[i].prim != kNoPrimitive) prefetch_hit(raw[i].prim);
        }
        for (std::size_t i = 0; i < m; ++i) decode(raw[i], s[b + i], x ? &x[b + i] : nullptr);
    }
}

// Closest hits of m <= 16 rays with valid fields (rays made by finish()) through
// Embree's 16-wide packet interface; unused lanes are masked off. Embree's hybrid
// packet traversal gives the same hits as rtcIntersect1 for these incoherent rays
// (checked bit for bit in the tests) at a lower cost per ray.
void EmbreeSource::Impl::intersect16(const Sample* s, std::size_t m, RawHit* raw) const {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    alignas(64) RTCRayHit16 pk;
    alignas(64) int valid[kLanes];
    for (std::size_t k = 0; k < kLanes; ++k) {
        valid[k] = k < m ? -1 : 0;
        pk.ray.time[k] = 0;
        pk.ray.mask[k] = kMeshMask;
        pk.ray.id[k] = 0;
        pk.ray.flags[k] = 0;
        pk.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
        pk.hit.primID[k] = RTC_INVALID_GEOMETRY_ID;
        pk.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
    }
    for (std::size_t k = 0; k < kLanes; ++k) {
        const format::Ray& r = s[std::min(k, m - 1)].ray;  // masked lanes repeat a valid ray
        pk.ray.org_x[k] = r.org[0];
        pk.ray.org_y[k] = r.org[1];
        pk.ray.org_z[k] = r.org[2];
        pk.ray.tnear[k] = r.tmin;
        pk.ray.dir_x[k] = r.dir[0];
        pk.ray.dir_y[k] = r.dir[1];
        pk.ray.dir_z[k] = r.dir[2];
        pk.ray.tfar[k] = r.tmax;
    }
    rtcIntersect16(valid, scene, &ctx, &pk);
    // The mask makes geomID kMeshGeometry = 0 (hit) or RTC_INVALID_GEOMETRY_ID (all ones, miss), so
    // or-ing it in gives kNoPrimitive for misses and masking with its complement
    // zeroes their (u, v): no branch on a coin flip per lane.
    static_assert(RTC_INVALID_GEOMETRY_ID == kNoPrimitive && kMeshGeometry == 0);
    for (std::size_t k = 0; k < m; ++k) {
        const std::uint32_t miss = pk.hit.geomID[k];
        raw[k] = {pk.ray.tfar[k], std::bit_cast<float>(std::bit_cast<std::uint32_t>(pk.hit.u[k]) & ~miss),
                  std::bit_cast<float>(std::bit_cast<std::uint32_t>(pk.hit.v[k]) & ~miss),
                  pk.hit.primID[k] | miss};
    }
}

// intersect16() over n rays (the packet baseline of measure_throughput()).
void EmbreeSource::Impl::intersect_packets(const Sample* s, std::size_t n, RawHit* raw) const {
    for (std::size_t b = 0; b < n; b += kLanes) intersect16(s + b, std::min(kLanes, n - b), raw + b);
}

// Ground truth for n <= kBatch rays made by finish() (valid by construction: no
// checks): all packets first, each hit's records prefetched as soon as its packet
// returns, then all decodes, so the record loads overlap the following traversals.
void EmbreeSource::Impl::trace_generated(Sample* s, SampleExtras* x, std::size_t n) const {
    RawHit raw[kBatch];
    for (std::size_t b = 0; b < n; b += kLanes) {
        const std::size_t m = std::min(kLanes, n - b);
        intersect16(s + b, m, raw + b);
        for (std::size_t i = b; i < b + m; ++i)  // a miss prefetches triangle 0 (no branch)
            prefetch_hit(raw[i].prim != kNoPrimitive ? raw[i].prim : 0);
    }
    for (std::size_t i = 0; i < n; ++i) decode(raw[i], s[i], x ? &x[i] : nullptr);
}

// ---- ray construction (the passes are described at Impl::Streams)

void EmbreeSource::Impl::draw(const Streams& st, std::size_t index, Pending& p) const {
    p.rng = stream(st.main, index);
    switch (index % 3) {
        case 1: {  // family (b): the alias slot and its coin
            double ut;
            p.rng.u01_pair(ut, p.coin);
            p.tri = std::uint32_t(std::min(triangles - 1, std::size_t(ut * double(triangles))));
            __builtin_prefetch(&surface[p.tri]);
            break;
        }
        case 2: {  // family (c): the first candidate; the cells of the first two
            p.candidate = uniform_in_box(p.rng);
            if (parity_ready && !packed_grid.empty()) {
                Rng ahead = p.rng;  // finish() draws the second candidate again
                const V3 second = uniform_in_box(ahead);
                p.cell[0] = std::uint32_t(cell_of(p.candidate));
                p.cell[1] = std::uint32_t(cell_of(second));
                __builtin_prefetch(&packed_grid[p.cell[0] >> 2]);
                __builtin_prefetch(&packed_grid[p.cell[1] >> 2]);
            }
            break;
        }
        default: break;
    }
}

void EmbreeSource::Impl::resolve(Pending& p) const {
    const SurfaceRecord& slot = surface[p.tri];
    if (!(p.coin < double(slot.keep))) {
        p.tri = slot.alias;
        __builtin_prefetch(&surface[p.tri]);
    }
}

// Family (a): origin on the sphere of radius 0.75 x diagonal around the box centre,
// aimed at a uniform point of the box. Writes the origin to `of`, returns the unit direction.
V3 EmbreeSource::Impl::outside_ray(Rng& rng, float of[3]) const {
    const V3 ctr{center[0], center[1], center[2]};
    const V3 o = ctr + (0.75 * diag) * uniform_sphere(rng);
    const V3 d = uniform_in_box(rng) - o;
    store_origin(o, of);
    return (1.0 / length(d)) * d;
}

// Family (b): leaves triangle p.tri (drawn by draw(), resolved by resolve()) from a
// uniform point on it, offset to a random side; the direction is cosine-weighted or
// uniform over that side's hemisphere. Writes the origin to `of` and the source triangle
// and side to x; returns the direction (unit up to rounding).
V3 EmbreeSource::Impl::surface_ray(Pending& p, float of[3], SampleExtras* x) const {
    Rng& rng = p.rng;
    const SurfaceRecord& rec = surface[p.tri];
    // Uniform point: b0 = 1 - sqrt(u1), b1 = u2 sqrt(u1) (Shirley 1990; PBRT §13.6.5).
    double u1, u2;
    rng.u01_pair(u1, u2);
    const double su = std::sqrt(u1);
    // With b0 = 1 - su: b2 = 1 - b0 - b1 = su - b1, and p = v0 + b1 e1 + b2 e2.
    const double b1 = u2 * su, b2 = su - b1;
    const V3 pt{rec.v0[0] + b1 * rec.e1[0] + b2 * rec.e2[0], rec.v0[1] + b1 * rec.e1[1] + b2 * rec.e2[1],
                rec.v0[2] + b1 * rec.e1[2] + b2 * rec.e2[2]};
    const float* fn = rec.ng;
    const std::uint64_t coins = rng.next();  // bit 63: side, bit 62: direction law
    const double side = (coins >> 63) ? 1.0 : -1.0;
    const V3 n = side * V3{fn[0], fn[1], fn[2]};
    const double eps =
        double(cfg.offset_diagonal) * diag +
        double(cfg.offset_relative) * std::max({std::abs(pt.x), std::abs(pt.y), std::abs(pt.z)});
    store_origin(pt + eps * n, of);
    if (x) {
        x->source_primitive = p.tri;
        x->side = std::int8_t(side);
    }
    // Unit up to rounding (n is a unit normal stored in float): no renormalization.
    return hemisphere(rng, n, (coins >> 62) & 1);
}

// Family (c): a uniform origin of the box, redrawn while the inside test puts it inside
// the solid (only when parity_ready), moved to the nearest box face after
// cfg.max_interior_attempts; direction uniform on the sphere. Writes the origin to `of`,
// counts candidates, votes and fallbacks into c; returns the direction.
V3 EmbreeSource::Impl::interior_ray(const Streams& st, std::size_t index, Pending& p, float of[3],
                                    std::vector<ParityHit>& hits, GenerateCounters& c) const {
    Rng& rng = p.rng;
    Rng votes{0};  // the vote stream, set up by the first vote
    bool votes_ready = false;
    auto vote_rng = [&]() -> Rng& {
        if (!votes_ready) votes = stream(st.votes, index), votes_ready = true;
        return votes;
    };
    for (std::uint32_t attempt = 0;;) {
        store_origin(attempt == 0 ? p.candidate : uniform_in_box(rng), of);  // the first one drawn by draw()
        ++c.interior_candidates;
        if (!parity_ready) break;
        // Classify the origin exactly as it will be stored (float).
        bool in;
        if (!packed_grid.empty()) {
            const unsigned state = cell_state(attempt < 2 ? p.cell[attempt] : cell_of(of));
            in = state ? state == 2 : parity_inside(of, vote_rng(), hits, c.parity_queries);
        } else {
            in = parity_inside(of, vote_rng(), hits, c.parity_queries);
        }
        if (!in) break;
        if (++attempt >= std::max<std::uint32_t>(1, cfg.max_interior_attempts)) {
            move_to_nearest_box_face(of);  // give up: outside the solid
            ++c.interior_fallbacks;
            break;
        }
    }
    return uniform_sphere(rng);  // unit up to rounding
}

// Moves `of` onto the box face nearest to it (ties: lowest axis, min face first).
void EmbreeSource::Impl::move_to_nearest_box_face(float of[3]) const {
    int best_axis = 0;
    bool best_hi = false;
    double best = INFINITY;
    for (int a = 0; a < 3; ++a) {
        const double dl = double(of[a]) - lo[a], dh = hi[a] - double(of[a]);
        if (dl < best) best = dl, best_axis = a, best_hi = false;
        if (dh < best) best = dh, best_axis = a, best_hi = true;
    }
    of[best_axis] = float(best_hi ? hi[best_axis] : lo[best_axis]);
}

// Builds sample `index` (family index % 3) from its pending state: the family's origin
// and direction, then the tmax draw, in the fixed stream order the determinism contract
// relies on. Ground-truth fields are left zero (trace_generated() fills them).
void EmbreeSource::Impl::finish(const Streams& st, std::size_t index, Pending& p, Sample& s, SampleExtras* x,
                                std::vector<ParityHit>& hits, GenerateCounters& c) const {
    s = Sample{};
    s.family = Family(index % 3);
    if (x) *x = SampleExtras{};
    float of[3] = {0, 0, 0};
    V3 d{};
    switch (s.family) {
        case Family::outside: d = outside_ray(p.rng, of); break;
        case Family::surface: d = surface_ray(p, of, x); break;
        case Family::interior: d = interior_ray(st, index, p, of, hits, c); break;
    }
    const double dd[3] = {d.x, d.y, d.z};
    for (int i = 0; i < 3; ++i) {
        s.ray.org[i] = of[i];
        s.ray.dir[i] = float(dd[i]);
    }
    s.ray.tmin = 0.0f;
    double u_shadow, u_tmax;
    p.rng.u01_pair(u_shadow, u_tmax);
    s.ray.tmax = u_shadow < double(cfg.shadow_fraction) ? float(u_tmax * diag) : INFINITY;
}

// Samples [b, e) of the seed's sequence, in batches of kBatch: draw, resolve (family
// (b) only), finish, then trace. Per-thread scratch (`hits`) and counters (c) are the
// caller's.
void EmbreeSource::Impl::generate_range(std::uint64_t seed, std::size_t b, std::size_t e, Sample* out,
                                        SampleExtras* extras, std::vector<ParityHit>& hits,
                                        GenerateCounters& c) const {
    const Streams st{stream_base(seed, kMainSalt), stream_base(seed, kVoteSalt)};
    Pending pending[kBatch];
    for (std::size_t i = b; i < e; i += kBatch) {
        const std::size_t m = std::min(e, i + kBatch) - i;
        for (std::size_t k = 0; k < m; ++k) draw(st, i + k, pending[k]);
        for (std::size_t k = (4 - i % 3) % 3; k < m; k += 3) resolve(pending[k]);  // (i + k) % 3 == 1
        for (std::size_t k = 0; k < m; ++k)
            finish(st, i + k, pending[k], out[i + k], extras ? &extras[i + k] : nullptr, hits, c);
        trace_generated(out + i, extras ? extras + i : nullptr, m);
    }
}

// ---- public entry points

void EmbreeSource::generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out) {
    generate(seed, count, out, nullptr);
}

void EmbreeSource::generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out,
                            std::vector<SampleExtras>* extras) {
    out.resize(count);
    if (extras) extras->resize(count);
    const Impl& m = *impl_;
    std::atomic<std::uint64_t> candidates{0}, queries{0}, fallbacks{0};
    parallel_chunks(count, base::resolve_threads(m.cfg.threads), [&](std::size_t b, std::size_t e) {
        std::vector<ParityHit> hits;
        GenerateCounters c;
        m.generate_range(seed, b, e, out.data(), extras ? extras->data() : nullptr, hits, c);
        candidates += c.interior_candidates;
        queries += c.parity_queries;
        fallbacks += c.interior_fallbacks;
    });
    impl_->counters = {candidates.load(), queries.load(), fallbacks.load()};
}

void EmbreeSource::trace(std::span<Sample> samples, std::span<SampleExtras> extras) const {
    const Impl& m = *impl_;
    const bool with_extras = extras.size() >= samples.size();
    parallel_chunks(samples.size(), base::resolve_threads(m.cfg.threads), [&](std::size_t b, std::size_t e) {
        m.trace_range(samples.data() + b, with_extras ? extras.data() + b : nullptr, e - b);
    });
}

}  // namespace lsnif::sampling
