/* Minimal C consumer of the lsnif runtime reader: open a .lsnif file, print its
 * dimensions and where the weight arrays live, then trace a fixed fan of rays through its
 * box and print what came back. Compiled as C99, so it proves that <lsnif/lsnif.h> is
 * plain C; tests/install/check_install.sh builds it against installed trees and packages.
 * Usage: lsnif_print_info FILE.lsnif */
#include <lsnif/lsnif.h>

#include <math.h>
#include <stdio.h>

enum { FAN = 16, RAYS = FAN * FAN };

/* Rays from a point in front of the box (-z side) to points spread over its back face:
 * every ray crosses the box, some the object. Prints the hit count and mean t. */
static int trace_fan(const lsnif_model* model, const lsnif_info* info) {
    static lsnif_ray rays[RAYS];
    static lsnif_hit hits[RAYS];
    const float* lo = info->box_min;
    const float* hi = info->box_max;
    for (int i = 0; i < FAN; ++i) {
        for (int j = 0; j < FAN; ++j) {
            lsnif_ray* r = &rays[i * FAN + j];
            const float u = (i + 0.5f) / FAN, v = (j + 0.5f) / FAN;
            const float target[3] = {lo[0] + u * (hi[0] - lo[0]), lo[1] + v * (hi[1] - lo[1]), hi[2]};
            r->org[0] = 0.5f * (lo[0] + hi[0]);
            r->org[1] = 0.5f * (lo[1] + hi[1]);
            r->org[2] = lo[2] - (hi[2] - lo[2]);
            for (int k = 0; k < 3; ++k) r->dir[k] = target[k] - r->org[k];
            r->tmin = 0.0f;
            r->tmax = INFINITY;
        }
    }
    const lsnif_status st = lsnif_intersect(model, rays, RAYS, hits);
    if (st != LSNIF_OK) {
        fprintf(stderr, "error: intersect failed (%s)\n", lsnif_status_string(st));
        return 1;
    }
    int hit_count = 0;
    double t_sum = 0.0;
    for (int k = 0; k < RAYS; ++k) {
        if (!hits[k].hit) continue;
        ++hit_count;
        t_sum += hits[k].t;
    }
    printf("fan: %d of %d rays hit, mean t %.4f\n", hit_count, RAYS, hit_count ? t_sum / hit_count : 0.0);
    return 0;
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
    uint32_t reads_major = 0, reads_minor = 0;
    const char* library = lsnif_version(&reads_major, &reads_minor);
    printf("library %s, reads format %u.%u\n", library, (unsigned)reads_major, (unsigned)reads_minor);
    lsnif_info info;
    lsnif_get_info(model, &info);
    printf("format %u.%u, %llu bytes\n", (unsigned)info.version_major, (unsigned)info.version_minor,
           (unsigned long long)info.file_size);
    printf("grid %u^3 (%llu occupied), H=%u, F=%u, T=2^%u, levels:", info.grid_resolution,
           (unsigned long long)info.occupied_voxels, info.max_points, info.features_per_level,
           info.log2_table_size);
    for (uint32_t l = 0; l < info.level_count; ++l) printf(" %u", info.level_resolution[l]);
    printf("\nmlp %u", info.input_width);
    for (uint32_t k = 0; k < info.hidden_layer_count; ++k) printf(" -> %u", info.hidden_width[k]);
    printf(" -> %u\n", info.output_count);
    /* A GPU implementation must append these inputs after the point features when the
     * model has them (FORMAT.md §8 steps 4a and 4b). */
    uint32_t ray_inputs = 0;
    lsnif_get_ray_inputs(model, &ray_inputs);
    printf("ray inputs:%s%s%s\n", ray_inputs ? "" : " none",
           ray_inputs & LSNIF_RAY_INPUT_DIRECTION ? " direction (3)" : "",
           ray_inputs & LSNIF_RAY_INPUT_ENTRY_OFFSETS ? " entry offsets (H)" : "");
    printf("box [%g %g %g] .. [%g %g %g]\n", info.box_min[0], info.box_min[1], info.box_min[2],
           info.box_max[0], info.box_max[1], info.box_max[2]);
    /* The arrays a GPU renderer would upload, with their shapes. */
    for (uint32_t k = 0; k < lsnif_layer_count(model); ++k) {
        lsnif_array w;
        if (lsnif_get_array(model, LSNIF_ARRAY_LAYER_WEIGHTS, k, &w) == LSNIF_OK)
            printf("layer %u weights fp16 [%llu x %llu] %llu bytes\n", k, (unsigned long long)w.dims[0],
                   (unsigned long long)w.dims[1], (unsigned long long)w.bytes);
    }
    size_t len = 0;
    lsnif_metadata(model, &len);
    printf("metadata %zu bytes, %llu parameters\n", len, (unsigned long long)info.parameter_count);
    /* The fp32 reference arithmetic (FORMAT.md section 8): the same hits on every CPU, so
     * builds of this program against different installs can be compared line by line. */
    lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, NULL);
    const int failed = trace_fan(model, &info);
    lsnif_close(model);
    return failed;
}
