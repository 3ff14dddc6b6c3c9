/* A renderer's use of the installed reader, in C: open an asset, shoot a fixed fan of rays
 * at its box with the fp32 reference arithmetic, print what came back. tests/install/
 * check_install.sh builds it against installed trees (CMake and plain pkg-config, static
 * and shared) and compares every build's output with the in-tree build's.
 * Usage: lsnif_consumer_c FILE.lsnif */
#include <lsnif/lsnif.h>

#include <math.h>
#include <stdio.h>

enum { FAN = 16, RAYS = FAN * FAN };

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
    lsnif_arithmetic in_use;
    lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, &in_use);
    lsnif_info info;
    lsnif_get_info(model, &info);

    /* Rays from a plane in front of the box (-z side) towards points spread over its
     * back face: every ray crosses the box, some the object. */
    static lsnif_ray rays[RAYS];
    static lsnif_hit hits[RAYS];
    const float* lo = info.box_min;
    const float* hi = info.box_max;
    for (int i = 0; i < FAN; ++i) {
        for (int j = 0; j < FAN; ++j) {
            lsnif_ray* r = &rays[i * FAN + j];
            float u = (i + 0.5f) / FAN, v = (j + 0.5f) / FAN;
            float target[3] = {lo[0] + u * (hi[0] - lo[0]), lo[1] + v * (hi[1] - lo[1]), hi[2]};
            r->org[0] = 0.5f * (lo[0] + hi[0]);
            r->org[1] = 0.5f * (lo[1] + hi[1]);
            r->org[2] = lo[2] - (hi[2] - lo[2]);
            for (int k = 0; k < 3; ++k) r->dir[k] = target[k] - r->org[k];
            r->tmin = 0.0f;
            r->tmax = INFINITY;
        }
    }
    st = lsnif_intersect(model, rays, RAYS, hits);
    if (st != LSNIF_OK) {
        fprintf(stderr, "error: %s: intersect failed (%s)\n", argv[1], lsnif_status_string(st));
        lsnif_close(model);
        return 1;
    }
    int hit_count = 0;
    double t_sum = 0.0;
    for (int k = 0; k < RAYS; ++k) {
        if (!hits[k].hit) continue;
        ++hit_count;
        t_sum += hits[k].t;
    }
    uint32_t major = 0, minor = 0;
    const char* library = lsnif_version(&major, &minor);
    printf("library %s reads %u.%u\n", library, (unsigned)major, (unsigned)minor);
    printf("grid %u^3, %u levels, mlp %u -> %u\n", info.grid_resolution, info.level_count, info.input_width,
           info.output_count);
    printf("%d of %d rays hit, mean t %.4f\n", hit_count, RAYS, hit_count ? t_sum / hit_count : 0.0);
    lsnif_close(model);
    return 0;
}
