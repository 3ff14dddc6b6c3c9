/* trace_rays ASSET RAYS HITS OCCLUDED: the C reader's answers to the rays of file RAYS
 * (lsnif_ray records), written as lsnif_hit records to HITS and one byte per ray to
 * OCCLUDED. What the Python module's answers are compared with (test_lsnif.py). C99. */
#include <lsnif/lsnif.h>
#include <stdio.h>
#include <stdlib.h>

static int fail(const char* what, const char* path) {
    fprintf(stderr, "error: %s: %s\n", path, what);
    return 1;
}

int main(int argc, char** argv) {
    if (argc != 5) {
        fprintf(stderr, "usage: trace_rays ASSET RAYS HITS OCCLUDED\n");
        return 2;
    }
    lsnif_model* model = NULL;
    lsnif_error error;
    if (lsnif_open_file(argv[1], &model, &error) != LSNIF_OK) return fail(error.message, argv[1]);
    FILE* in = fopen(argv[2], "rb");
    if (!in) return fail("cannot open", argv[2]);
    fseek(in, 0, SEEK_END);
    const long bytes = ftell(in);
    fseek(in, 0, SEEK_SET);
    const size_t n = (size_t)bytes / sizeof(lsnif_ray);
    lsnif_ray* rays = malloc(n * sizeof *rays + 1);
    lsnif_hit* hits = malloc(n * sizeof *hits + 1);
    uint8_t* occluded = malloc(n + 1);
    if (!rays || !hits || !occluded) return fail("out of memory", argv[2]);
    if (fread(rays, sizeof *rays, n, in) != n) return fail("short read", argv[2]);
    fclose(in);
    if (lsnif_intersect(model, rays, n, hits) != LSNIF_OK) return fail("lsnif_intersect failed", argv[1]);
    if (lsnif_occluded(model, rays, n, occluded) != LSNIF_OK) return fail("lsnif_occluded failed", argv[1]);
    FILE* out = fopen(argv[3], "wb");
    if (!out || fwrite(hits, sizeof *hits, n, out) != n || fclose(out) != 0)
        return fail("cannot write", argv[3]);
    out = fopen(argv[4], "wb");
    if (!out || fwrite(occluded, 1, n, out) != n || fclose(out) != 0) return fail("cannot write", argv[4]);
    free(rays);
    free(hits);
    free(occluded);
    lsnif_close(model);
    return 0;
}
