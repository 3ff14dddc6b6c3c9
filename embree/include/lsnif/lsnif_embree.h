/*
 * lsnif_embree.h — LSNIF assets as Embree 3 user geometries (C API).
 *
 * A companion of the reader (lsnif.h) for renderers that already trace through Embree. It
 * puts an open asset, placed by an object-to-world transform, into an Embree scene as a
 * geometry of type RTC_GEOMETRY_TYPE_USER with one primitive, so that the renderer's own
 * rtcIntersect1/4/8/16, rtcOccluded1/4/8/16 and stream calls hit assets and triangle meshes
 * in one traversal. It is a separate library because it links Embree; the reader does not
 * (it depends on zstd only). Valid C99 and C++; it never throws, aborts or exits.
 *
 * What the geometry answers, per ray Embree hands it (single rays and packets of any width,
 * inactive lanes untouched):
 *   intersect  the asset is evaluated on the ray from its tnear to +infinity, as
 *              lsnif_intersect_instance answers a ray with tmax = +INFINITY; a hit at t in
 *              [tnear, tfar] is offered to the intersection filter functions (the
 *              geometry's and the context's, through rtcFilterIntersection) and, if none
 *              rejects it, becomes the ray's hit. The answer does not depend on what Embree
 *              met before along the ray, so it is the same in any traversal order; for rays
 *              with tmax = +INFINITY it is exactly lsnif_intersect_instance's.
 *   occluded   the asset is evaluated on [tnear, tfar], the decision lsnif_occluded_instance
 *              reports for the same ray, bit for bit; a hit is offered to the occlusion
 *              filter functions (rtcFilterOcclusion) with its distance, normal and material,
 *              and an accepted one sets tfar to -infinity, as Embree's own geometries do.
 *              With the model's enclosed rule on (lsnif_set_enclosed_rule), the decision
 *              is lsnif_occluded_instance's under the rule, and an occluded ray's tfar is
 *              set to -infinity without the occlusion filter functions: the rule decides
 *              some rays without a distance or normal to show them. A renderer that
 *              needs occlusion filters on an asset's geometry leaves the rule off.
 * A hit writes: tfar = the ray parameter of the hit; Ng = the asset's unit shading normal,
 * in the space of the rays the geometry receives (the scene's, or the instance's local
 * space when the geometry sits in a scene instanced by Embree, like a triangle's Ng);
 * u = v = 0; primID = the asset's material index (0 without materials: the asset is one
 * primitive, so primID carries what a triangle mesh's primID would be used to look up);
 * geomID = the geometry's ID; instID[0] = the context's current instance ID.
 *
 * Speed: each call evaluates the asset on the 1 to 16 rays of one Embree call, while
 * lsnif_intersect_instance is fastest on batches of >= 256 rays (docs/packaging.md "Assets
 * in an Embree scene" compares the two on the same render).
 */
#ifndef LSNIF_LSNIF_EMBREE_H
#define LSNIF_LSNIF_EMBREE_H

#include <embree3/rtcore.h>
#include <lsnif/lsnif.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Creates a committed user geometry on `device` that traces `model` placed by
 * `object_to_world`, a 3x4 row-major affine matrix [A | b] (x_world = A x_object + b) as
 * lsnif_intersect_instance takes it, or NULL for object space. Attach it with
 * rtcAttachGeometry or rtcAttachGeometryByID (one model may back any number of geometries);
 * release it with lsnif_embree_release_geometry, never with rtcReleaseGeometry alone.
 *
 * Ownership: `model` is borrowed. It must stay open, and its arithmetic unchanged
 * (lsnif_set_arithmetic), while any scene holding the geometry is traced; the transform is
 * copied. Tracing is safe from any number of threads, as the reader's.
 *
 * Returns LSNIF_ERR_INVALID_ARGUMENT for a NULL `device`, `model` or `out`, and for a
 * singular or non-finite transform; LSNIF_ERR_INTERNAL when Embree cannot create the
 * geometry (rtcGetDeviceError names why); LSNIF_ERR_OUT_OF_MEMORY. On failure `*out` is
 * NULL. */
lsnif_status lsnif_embree_new_geometry(RTCDevice device, const lsnif_model* model,
                                       const float object_to_world[12], RTCGeometry* out);

/* Releases a geometry made by lsnif_embree_new_geometry: the caller's reference and the
 * placement it keeps. Call it once every scene it was attached to has been released or has
 * detached it (scenes hold their own references, which outlive this call, but not the
 * placement). NULL is allowed. */
void lsnif_embree_release_geometry(RTCGeometry geometry);

#ifdef __cplusplus
}
#endif

#endif /* LSNIF_LSNIF_EMBREE_H */
