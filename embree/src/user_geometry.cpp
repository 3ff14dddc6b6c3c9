// The Embree user geometry of lsnif_embree.h: Embree's bounds, intersect and occluded
// callbacks answered by the reader's C API (lsnif_intersect / lsnif_intersect_instance, and
// lsnif_occluded / lsnif_occluded_instance under the enclosed rule), one call per Embree call
// with that call's active lanes.
#include <lsnif/lsnif_embree.h>

#include <lsnif/base/affine.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <new>

namespace {

// Embree 3's widest packet: its callbacks receive N = 1, 4, 8 or 16 lanes (rtcIntersect1 to
// rtcIntersect16; the stream calls are traced as such packets).
constexpr unsigned kLanes = 16;

// What a geometry keeps: its geometryUserPtr. Owned by the geometry's creator, freed by
// lsnif_embree_release_geometry.
struct Placement {
    const lsnif_model* model;
    bool has_transform;
    float object_to_world[12];
    RTCBounds bounds;
};

// The active lanes of one Embree call as reader rays, and the reader's answers.
struct LaneRays {
    unsigned lane[kLanes];
    lsnif_ray ray[kLanes];
    lsnif_hit hit[kLanes];
    unsigned count = 0;
};

// Gathers the active lanes (valid = -1) of an Embree ray packet of width N <= kLanes;
// `tmax_infinite` evaluates them to +infinity (the intersect rule of lsnif_embree.h).
void gather(const int* valid, RTCRayN* rays, unsigned N, bool tmax_infinite, LaneRays& out) {
    out.count = 0;
    for (unsigned i = 0; i < N; ++i) {
        if (valid[i] != -1) continue;
        lsnif_ray& r = out.ray[out.count];
        r.org[0] = RTCRayN_org_x(rays, N, i);
        r.org[1] = RTCRayN_org_y(rays, N, i);
        r.org[2] = RTCRayN_org_z(rays, N, i);
        r.tmin = RTCRayN_tnear(rays, N, i);
        r.dir[0] = RTCRayN_dir_x(rays, N, i);
        r.dir[1] = RTCRayN_dir_y(rays, N, i);
        r.dir[2] = RTCRayN_dir_z(rays, N, i);
        r.tmax = tmax_infinite ? std::numeric_limits<float>::infinity() : RTCRayN_tfar(rays, N, i);
        out.lane[out.count++] = i;
    }
}

// The reader on the gathered rays; false when it refuses them (then nothing is hit).
bool trace(const Placement& p, LaneRays& rays) {
    if (rays.count == 0) return true;
    const lsnif_status s =
        p.has_transform ? lsnif_intersect_instance(p.model, p.object_to_world, rays.ray, rays.count, rays.hit)
                        : lsnif_intersect(p.model, rays.ray, rays.count, rays.hit);
    return s == LSNIF_OK;
}

// Lane i of a hit record of width N (Embree's SOA layout) set to the asset's hit `h`
// (lsnif_embree.h says what each field carries).
void write_hit(RTCHitN* hit, unsigned N, unsigned i, const lsnif_hit& h, unsigned geom_id,
               const RTCIntersectContext& context) {
    RTCHitN_Ng_x(hit, N, i) = h.normal[0];
    RTCHitN_Ng_y(hit, N, i) = h.normal[1];
    RTCHitN_Ng_z(hit, N, i) = h.normal[2];
    RTCHitN_u(hit, N, i) = 0.0f;
    RTCHitN_v(hit, N, i) = 0.0f;
    RTCHitN_primID(hit, N, i) = h.material;
    RTCHitN_geomID(hit, N, i) = geom_id;
    for (unsigned l = 0; l < RTC_MAX_INSTANCE_LEVEL_COUNT; ++l)
        RTCHitN_instID(hit, N, i, l) = context.instID[l];
}

// Hit records of one packet of width N (floats and uints, Embree's SOA layout), for the
// filter functions to read before a hit is committed.
struct CandidateHits {
    static constexpr unsigned kWords =
        7 + RTC_MAX_INSTANCE_LEVEL_COUNT;  // Ng xyz, u, v, primID, geomID, instID
    alignas(64) std::array<std::uint32_t, kWords * kLanes> words{};
    RTCHitN* get() { return reinterpret_cast<RTCHitN*>(words.data()); }
};

// The filter functions' view of a slice of candidate hits, with the ray's tfar set to each
// candidate's t meanwhile (what a filter function reads); Embree's contract for user
// geometries (rtcFilterIntersection, rtcFilterOcclusion) is to restore tfar where a filter
// rejects. valid[i] = -1 marks lane i's candidate, and stays -1 if it is accepted.
struct Judged {
    int valid[kLanes] = {};
    bool proposed[kLanes] = {};
    float old_tfar[kLanes];
    CandidateHits hits;
    bool any = false;
};

// Offers lane i's hit `h` to the filters (see Judged).
void propose(Judged& j, RTCRayN* rays, unsigned N, unsigned i, const lsnif_hit& h, unsigned geom_id,
             const RTCIntersectContext& context) {
    write_hit(j.hits.get(), N, i, h, geom_id, context);
    j.valid[i] = -1;
    j.proposed[i] = true;
    j.old_tfar[i] = RTCRayN_tfar(rays, N, i);
    RTCRayN_tfar(rays, N, i) = h.t;
    j.any = true;
}

RTCFilterFunctionNArguments filter_arguments(Judged& j, void* user, RTCIntersectContext* context,
                                             RTCRayN* rays, unsigned N) {
    RTCFilterFunctionNArguments f;
    f.valid = j.valid;
    f.geometryUserPtr = user;
    f.context = context;
    f.ray = rays;
    f.hit = j.hits.get();
    f.N = N;
    return f;
}

// An intersect call: the reader on the active lanes to +infinity, then every hit in
// [tnear, tfar] judged by the filters and the accepted ones committed.
void intersect_packet(const RTCIntersectFunctionNArguments* args, const Placement& p) {
    const unsigned N = args->N;
    RTCRayN* rays = RTCRayHitN_RayN(args->rayhit, N);
    LaneRays lr;
    gather(args->valid, rays, N, true, lr);
    if (!trace(p, lr)) return;
    Judged j;
    for (unsigned k = 0; k < lr.count; ++k) {
        const lsnif_hit& h = lr.hit[k];
        const unsigned i = lr.lane[k];
        if (h.hit && h.t >= lr.ray[k].tmin && h.t <= RTCRayN_tfar(rays, N, i))
            propose(j, rays, N, i, h, args->geomID, *args->context);
    }
    if (!j.any) return;
    const RTCFilterFunctionNArguments fargs =
        filter_arguments(j, args->geometryUserPtr, args->context, rays, N);
    rtcFilterIntersection(args, &fargs);
    RTCHitN* hits = RTCRayHitN_HitN(args->rayhit, N);
    for (unsigned k = 0; k < lr.count; ++k) {
        const unsigned i = lr.lane[k];
        if (!j.proposed[i]) continue;
        if (j.valid[i] == -1)
            write_hit(hits, N, i, lr.hit[k], args->geomID, *args->context);
        else
            RTCRayN_tfar(rays, N, i) = j.old_tfar[i];
    }
}

// An occluded call under the model's enclosed rule: lsnif_occluded(_instance) decides, the
// rule included, and an occluded ray is marked without the filters (lsnif_embree.h): a ray
// the rule takes has no distance or normal to show them.
void occluded_by_rule(const RTCOccludedFunctionNArguments* args, const Placement& p) {
    const unsigned N = args->N;
    RTCRayN* rays = args->ray;
    LaneRays lr;
    gather(args->valid, rays, N, false, lr);
    if (lr.count == 0) return;
    std::uint8_t occluded[kLanes];
    const lsnif_status s =
        p.has_transform ? lsnif_occluded_instance(p.model, p.object_to_world, lr.ray, lr.count, occluded)
                        : lsnif_occluded(p.model, lr.ray, lr.count, occluded);
    if (s != LSNIF_OK) return;
    for (unsigned k = 0; k < lr.count; ++k)
        if (occluded[k]) RTCRayN_tfar(rays, N, lr.lane[k]) = -std::numeric_limits<float>::infinity();
}

// An occluded call: the reader's hit decision on [tnear, tfar] (lsnif_intersect decides as
// lsnif_occluded does, bit for bit, and also gives the filters a distance, normal and
// material); an accepted hit marks the ray occluded (tfar = -infinity, Embree's convention).
void occluded_packet(const RTCOccludedFunctionNArguments* args, const Placement& p) {
    if (lsnif_get_enclosed_rule(p.model)) return occluded_by_rule(args, p);
    const unsigned N = args->N;
    RTCRayN* rays = args->ray;
    LaneRays lr;
    gather(args->valid, rays, N, false, lr);
    if (!trace(p, lr)) return;
    Judged j;
    for (unsigned k = 0; k < lr.count; ++k)
        if (lr.hit[k].hit) propose(j, rays, N, lr.lane[k], lr.hit[k], args->geomID, *args->context);
    if (!j.any) return;
    const RTCFilterFunctionNArguments fargs =
        filter_arguments(j, args->geometryUserPtr, args->context, rays, N);
    rtcFilterOcclusion(args, &fargs);
    for (unsigned i = 0; i < N; ++i)
        if (j.proposed[i])
            RTCRayN_tfar(rays, N, i) =
                j.valid[i] == -1 ? -std::numeric_limits<float>::infinity() : j.old_tfar[i];
}

extern "C" void placement_bounds(const RTCBoundsFunctionArguments* args) {
    *args->bounds_o = static_cast<const Placement*>(args->geometryUserPtr)->bounds;
}

extern "C" void placement_intersect(const RTCIntersectFunctionNArguments* args) {
    if (args->N <= kLanes) intersect_packet(args, *static_cast<const Placement*>(args->geometryUserPtr));
}

extern "C" void placement_occluded(const RTCOccludedFunctionNArguments* args) {
    if (args->N <= kLanes) occluded_packet(args, *static_cast<const Placement*>(args->geometryUserPtr));
}

// The asset's box mapped by the transform: the box of its eight corners, rounded outward
// (the corners are computed in double, then each bound moves one float step out) so that
// Embree never culls a ray the asset's own box clipping would keep.
RTCBounds world_bounds(const lsnif_info& info, const float* m) {
    double lo[3], hi[3];
    for (int a = 0; a < 3; ++a) lo[a] = INFINITY, hi[a] = -INFINITY;
    for (int c = 0; c < 8; ++c) {
        const double p[3] = {c & 1 ? info.box_max[0] : info.box_min[0],
                             c & 2 ? info.box_max[1] : info.box_min[1],
                             c & 4 ? info.box_max[2] : info.box_min[2]};
        for (int r = 0; r < 3; ++r) {
            const double w =
                m ? m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3] : p[r];
            lo[r] = std::min(lo[r], w);
            hi[r] = std::max(hi[r], w);
        }
    }
    RTCBounds b{};
    float* lower[3] = {&b.lower_x, &b.lower_y, &b.lower_z};
    float* upper[3] = {&b.upper_x, &b.upper_y, &b.upper_z};
    for (int a = 0; a < 3; ++a) {
        *lower[a] = std::nextafter(float(lo[a]), -INFINITY);
        *upper[a] = std::nextafter(float(hi[a]), INFINITY);
    }
    return b;
}

}  // namespace

extern "C" lsnif_status lsnif_embree_new_geometry(RTCDevice device, const lsnif_model* model,
                                                  const float object_to_world[12], RTCGeometry* out) {
    if (!out) return LSNIF_ERR_INVALID_ARGUMENT;
    *out = nullptr;
    if (!device || !model) return LSNIF_ERR_INVALID_ARGUMENT;
    if (object_to_world && !lsnif::base::invert_linear(object_to_world)) return LSNIF_ERR_INVALID_ARGUMENT;
    lsnif_info info;
    if (const lsnif_status s = lsnif_get_info(model, &info); s != LSNIF_OK) return s;

    Placement* p = new (std::nothrow)
        Placement{model, object_to_world != nullptr, {}, world_bounds(info, object_to_world)};
    if (!p) return LSNIF_ERR_OUT_OF_MEMORY;
    if (object_to_world) std::copy(object_to_world, object_to_world + 12, p->object_to_world);
    for (const float v : {p->bounds.lower_x, p->bounds.lower_y, p->bounds.lower_z, p->bounds.upper_x,
                          p->bounds.upper_y, p->bounds.upper_z})
        if (!std::isfinite(v)) {  // a finite transform of a finite box that overflows float
            delete p;
            return LSNIF_ERR_INVALID_ARGUMENT;
        }

    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_USER);
    if (!g) {
        delete p;
        return LSNIF_ERR_INTERNAL;
    }
    rtcSetGeometryUserPrimitiveCount(g, 1);
    rtcSetGeometryUserData(g, p);
    rtcSetGeometryBoundsFunction(g, placement_bounds, nullptr);
    rtcSetGeometryIntersectFunction(g, placement_intersect);
    rtcSetGeometryOccludedFunction(g, placement_occluded);
    rtcCommitGeometry(g);
    *out = g;
    return LSNIF_OK;
}

extern "C" void lsnif_embree_release_geometry(RTCGeometry geometry) {
    if (!geometry) return;
    delete static_cast<Placement*>(rtcGetGeometryUserData(geometry));
    rtcSetGeometryUserData(geometry, nullptr);
    rtcReleaseGeometry(geometry);
}
