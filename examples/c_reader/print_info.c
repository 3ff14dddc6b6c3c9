/* Minimal C consumer of the lsnif runtime reader: open a .lsnif file, print its
 * dimensions and where the weight arrays live. Compiled as C99, so it proves that
 * <lsnif/lsnif.h> is plain C. Usage: lsnif_print_info FILE.lsnif */
#include <lsnif/lsnif.h>

#include <stdio.h>

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
    printf("format %u.%u, %llu bytes\n", (unsigned)info.version_major, (unsigned)info.version_minor,
           (unsigned long long)info.file_size);
    printf("grid %u^3 (%llu occupied), H=%u, F=%u, T=2^%u, levels:", info.grid_resolution,
           (unsigned long long)info.occupied_voxels, info.max_points, info.features_per_level,
           info.log2_table_size);
    for (uint32_t l = 0; l < info.level_count; ++l) printf(" %u", info.level_resolution[l]);
    printf("\nmlp %u", info.input_width);
    for (uint32_t k = 0; k < info.hidden_layer_count; ++k) printf(" -> %u", info.hidden_width[k]);
    printf(" -> %u\n", info.output_count);
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
    lsnif_close(model);
    return 0;
}
