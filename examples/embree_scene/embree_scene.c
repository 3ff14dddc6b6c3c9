/* An LSNIF asset in an Embree scene (lsnif_embree.h): the asset, placed by a transform, and
 * a triangle floor under it are traced by Embree's own rtcIntersect1 and rtcOccluded1, the
 * way a renderer that already uses Embree would add an asset. Compiled as C99, so it proves
 * that <lsnif/lsnif_embree.h> is plain C; tests/install/check_install.sh builds it against
 * installed trees and packages.
 * Usage: lsnif_embree_scene FILE.lsnif */
#include <lsnif/lsnif_embree.h>

#include <math.h>
#include <stdio.h>

enum { FAN = 16 };

/* A floor quad just under the placed asset's world box (y = floor_y), four times as wide. */
static RTCGeometry make_floor(RTCDevice device, const float lo[3], const float hi[3], float floor_y) {
    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    float* v = (float*)rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                               3 * sizeof(float), 4);
    unsigned* t = (unsigned*)rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                     3 * sizeof(unsigned), 2);
    if (!v || !t) {
        rtcReleaseGeometry(g);
        return NULL;
    }
    const float cx = 0.5f * (lo[0] + hi[0]), cz = 0.5f * (lo[2] + hi[2]);
    const float r = 2.0f * fmaxf(hi[0] - lo[0], hi[2] - lo[2]);
    const float corners[12] = {cx - r, floor_y, cz - r, cx + r, floor_y, cz - r,
                               cx + r, floor_y, cz + r, cx - r, floor_y, cz + r};
    const unsigned index[6] = {0, 1, 2, 0, 2, 3};
    for (int k = 0; k < 12; ++k) v[k] = corners[k];
    for (int k = 0; k < 6; ++k) t[k] = index[k];
    rtcCommitGeometry(g);
    return g;
}

/* A fan of rays from a point above and in front of the asset, down across it onto the floor;
 * from each hit a shadow ray towards a light above. Prints what each ray met. */
static void trace_fan(RTCScene scene, unsigned asset_id, const float lo[3], const float hi[3]) {
    const float eye[3] = {0.5f * (lo[0] + hi[0]), hi[1] + (hi[1] - lo[1]), lo[2] - 2.0f * (hi[2] - lo[2])};
    const float light[3] = {eye[0], hi[1] + 4.0f * (hi[1] - lo[1]), 0.5f * (lo[2] + hi[2])};
    int on_asset = 0, on_floor = 0, shadowed = 0;
    double t_sum = 0.0;
    for (int i = 0; i < FAN; ++i)
        for (int j = 0; j < FAN; ++j) {
            const float u = (i + 0.5f) / FAN, w = (j + 0.5f) / FAN;
            const float target[3] = {lo[0] + u * (hi[0] - lo[0]), lo[1], lo[2] + w * (hi[2] - lo[2])};
            struct RTCIntersectContext context;
            rtcInitIntersectContext(&context);
            struct RTCRayHit rh;
            rh.ray.org_x = eye[0], rh.ray.org_y = eye[1], rh.ray.org_z = eye[2];
            rh.ray.dir_x = target[0] - eye[0], rh.ray.dir_y = target[1] - eye[1],
            rh.ray.dir_z = target[2] - eye[2];
            rh.ray.tnear = 0.0f, rh.ray.tfar = INFINITY, rh.ray.time = 0.0f;
            rh.ray.mask = 0xFFFFFFFFu, rh.ray.id = 0, rh.ray.flags = 0;
            rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
            rtcIntersect1(scene, &context, &rh);
            if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) continue;
            if (rh.hit.geomID == asset_id) {
                ++on_asset;
                t_sum += rh.ray.tfar;
            } else {
                ++on_floor;
            }
            /* The shadow ray leaves the hit point a little along the normal, facing the eye. */
            const float p[3] = {eye[0] + rh.ray.tfar * rh.ray.dir_x, eye[1] + rh.ray.tfar * rh.ray.dir_y,
                                eye[2] + rh.ray.tfar * rh.ray.dir_z};
            float n[3] = {rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z};
            const float len = sqrtf(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
            const float facing =
                n[0] * rh.ray.dir_x + n[1] * rh.ray.dir_y + n[2] * rh.ray.dir_z > 0 ? -1.0f : 1.0f;
            const float eps = 1e-3f * (hi[1] - lo[1]);
            struct RTCRay shadow;
            shadow.org_x = p[0] + facing * eps * n[0] / len;
            shadow.org_y = p[1] + facing * eps * n[1] / len;
            shadow.org_z = p[2] + facing * eps * n[2] / len;
            shadow.dir_x = light[0] - shadow.org_x, shadow.dir_y = light[1] - shadow.org_y;
            shadow.dir_z = light[2] - shadow.org_z;
            shadow.tnear = 0.0f, shadow.tfar = 1.0f, shadow.time = 0.0f;
            shadow.mask = 0xFFFFFFFFu, shadow.id = 0, shadow.flags = 0;
            rtcInitIntersectContext(&context);
            rtcOccluded1(scene, &context, &shadow);
            shadowed += shadow.tfar < 0.0f; /* Embree marks an occluded ray with tfar = -inf */
        }
    printf("fan: %d of %d rays hit the asset (mean t %.4f), %d the floor; %d shadow rays occluded\n",
           on_asset, FAN * FAN, on_asset ? t_sum / on_asset : 0.0, on_floor, shadowed);
}

int main(int argc, char** argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s FILE.lsnif\n", argv[0]);
        return 2;
    }
    lsnif_model* model = NULL;
    lsnif_error err;
    lsnif_status st = lsnif_open_file(argv[1], &model, &err);
    if (st != LSNIF_OK) {
        fprintf(stderr, "error: %s: %s (%s)\n", argv[1], err.message, lsnif_status_string(st));
        return 1;
    }
    lsnif_info info;
    lsnif_get_info(model, &info);
    /* The asset twice as large and moved up by its own height: world box [lo, hi]. */
    const float height = info.box_max[1] - info.box_min[1];
    const float object_to_world[12] = {2, 0, 0, 0, 0, 2, 0, height, 0, 0, 2, 0};
    float lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        lo[a] = 2.0f * info.box_min[a] + (a == 1 ? height : 0.0f);
        hi[a] = 2.0f * info.box_max[a] + (a == 1 ? height : 0.0f);
    }

    int status = 1;
    RTCDevice device = rtcNewDevice(NULL);
    RTCScene scene = device ? rtcNewScene(device) : NULL;
    RTCGeometry asset = NULL, floor_quad = NULL;
    if (!scene) {
        fprintf(stderr, "error: embree: cannot create a device\n");
        goto done;
    }
    st = lsnif_embree_new_geometry(device, model, object_to_world, &asset);
    if (st != LSNIF_OK) {
        fprintf(stderr, "error: %s: cannot make an Embree geometry (%s)\n", argv[1], lsnif_status_string(st));
        goto done;
    }
    floor_quad = make_floor(device, lo, hi, lo[1] - 0.01f * height);
    if (!floor_quad) {
        fprintf(stderr, "error: embree: cannot make the floor\n");
        goto done;
    }
    const unsigned asset_id = rtcAttachGeometry(scene, asset);
    rtcAttachGeometry(scene, floor_quad);
    rtcCommitScene(scene);
    trace_fan(scene, asset_id, lo, hi);
    status = 0;
done:
    if (scene) rtcReleaseScene(scene);
    if (floor_quad) rtcReleaseGeometry(floor_quad);
    lsnif_embree_release_geometry(asset);
    if (device) rtcReleaseDevice(device);
    lsnif_close(model);
    return status;
}
