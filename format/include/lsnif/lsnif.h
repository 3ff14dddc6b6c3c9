/*
 * lsnif.h — runtime reader for .lsnif neural intersection assets (C API).
 *
 * This is the whole interface a renderer links against. It depends on zstd only,
 * is valid C99 and C++, and never throws, aborts or exits: every function reports
 * through an lsnif_status. The binary layout it reads is specified in
 * schema/FORMAT.md; nothing here assumes model defaults — every dimension comes
 * from the file.
 *
 * Ownership: an lsnif_model owns a decoded copy of every section. Pointers returned
 * by the accessors stay valid until lsnif_close() on that handle. A handle may be
 * read from several threads at once (no accessor mutates it).
 *
 * NULL: each function states which pointers may be NULL. Passing NULL anywhere else
 * returns LSNIF_ERR_INVALID_ARGUMENT (functions returning a value return 0 or NULL
 * instead, as stated); nothing is dereferenced first.
 *
 * Per-thread scratch: lsnif_intersect and lsnif_intersect_instance keep their working
 * buffers (feature points, network inputs and activations for 256 rays at a time) in
 * thread-local storage, so concurrent calls share nothing and a hot loop allocates
 * nothing after its first call. Each calling thread keeps them, sized for the largest
 * model it has traced, until the thread exits: about 0.7 MiB for the v1 model (330 KiB
 * of feature points, whatever the model, plus 256 * (input width + 2 * widest layer)
 * floats).
 */
#ifndef LSNIF_LSNIF_H
#define LSNIF_LSNIF_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#if defined(_WIN32) && defined(LSNIF_FORMAT_SHARED)
#define LSNIF_API __declspec(dllexport)
#elif defined(__GNUC__)
#define LSNIF_API __attribute__((visibility("default")))
#else
#define LSNIF_API
#endif

/* Container version this reader implements. It reads any file of the same major
 * version whose minor version is <= LSNIF_VERSION_MINOR. Writers of this library write
 * the lowest version that can express a model (FORMAT.md §2.4): 1.0 for fp16 grids
 * without ray inputs, 1.1 for quantized grids, 1.2 for ray inputs. */
#define LSNIF_VERSION_MAJOR 1
#define LSNIF_VERSION_MINOR 2

/* Hard limits of the v1 model descriptor (FORMAT.md §5). */
#define LSNIF_MAX_LEVELS 8
#define LSNIF_MAX_HIDDEN_LAYERS 8

/* Status codes are frozen: a value never changes meaning and new codes are only
 * appended, so a program may store or switch on them across library versions. */
typedef enum lsnif_status {
    LSNIF_OK = 0,
    LSNIF_ERR_INVALID_ARGUMENT = 1,  /* NULL pointer, bad index, bad size from the caller */
    LSNIF_ERR_IO = 2,                /* file could not be opened or read */
    LSNIF_ERR_NOT_LSNIF = 3,         /* magic number does not match */
    LSNIF_ERR_TRANSFER_DAMAGE = 4,   /* magic shows text-mode / 7-bit transfer damage */
    LSNIF_ERR_TRUNCATED = 5,         /* file shorter than its header or table declares */
    LSNIF_ERR_VERSION_NEWER = 6,     /* written by a newer lsnif: upgrade the reader */
    LSNIF_ERR_VERSION_OLDER = 7,     /* written by an older, unsupported lsnif: re-convert */
    LSNIF_ERR_CHECKSUM = 8,          /* a header, table or section checksum does not match */
    LSNIF_ERR_RESERVED = 9,          /* a reserved field or padding byte is not zero */
    LSNIF_ERR_LIMIT = 10,            /* a declared size exceeds a hard limit */
    LSNIF_ERR_LAYOUT = 11,           /* offsets/sizes overlap, misalign or leave the file */
    LSNIF_ERR_MISSING_SECTION = 12,  /* a section required by v1 is absent */
    LSNIF_ERR_UNKNOWN_REQUIRED = 13, /* a section marked required is unknown to this reader */
    LSNIF_ERR_DECOMPRESS = 14,       /* zstd payload is malformed or has the wrong size */
    LSNIF_ERR_MODEL = 15,            /* model descriptor inconsistent or out of range */
    LSNIF_ERR_NONFINITE = 16,        /* a weight or box value is NaN or infinite */
    LSNIF_ERR_OUT_OF_MEMORY = 17,
    LSNIF_ERR_INTERNAL = 18
} lsnif_status;

/* Static English name of a status ("ok", "checksum mismatch", ...). Never NULL, also
 * for values this library does not know ("unknown status"). */
LSNIF_API const char* lsnif_status_string(lsnif_status status);

/* The linked library's version, which may differ from the header a program was
 * compiled with (a shared library upgraded underneath it). Returns the release as a
 * static "MAJOR.MINOR.PATCH" string and writes the container version it reads, the
 * runtime value of LSNIF_VERSION_MAJOR / LSNIF_VERSION_MINOR. Either pointer may be
 * NULL. */
LSNIF_API const char* lsnif_version(uint32_t* container_major, uint32_t* container_minor);

/* Optional detail for a failure: pass a pointer to one of these to the open and
 * scan functions (or NULL when the status is enough). On failure `message` names the structure and field at
 * fault and `offset` the file offset involved (or UINT64_MAX when none applies). */
typedef struct lsnif_error {
    lsnif_status status;
    uint32_t reserved;
    uint64_t offset;
    char message[256];
} lsnif_error;

/* ---- Container-level view (what `lsnif inspect` shows) ------------------------ */

typedef enum lsnif_compression { LSNIF_COMPRESSION_NONE = 0, LSNIF_COMPRESSION_ZSTD = 1 } lsnif_compression;

#define LSNIF_SECTION_REQUIRED 1u

typedef struct lsnif_section_info {
    char tag[5];             /* four ASCII characters plus NUL */
    uint8_t known;           /* 1 if this reader understands the tag */
    uint8_t checksum_ok;     /* 1 if the payload verified completely: both CRC-32C and decoding */
    uint8_t decoded;         /* 1 if decompression ran and produced exactly raw_size bytes
                                (0 when the stored-bytes checksum failed first) */
    uint32_t payload_status; /* LSNIF_OK, LSNIF_ERR_CHECKSUM or LSNIF_ERR_DECOMPRESS */
    uint32_t flags;          /* LSNIF_SECTION_REQUIRED, ... */
    uint32_t compression;    /* lsnif_compression */
    uint64_t offset;         /* byte offset of the stored payload in the file */
    uint64_t stored_size;    /* bytes in the file */
    uint64_t raw_size;       /* bytes after decompression */
    uint32_t stored_crc32c;
    uint32_t raw_crc32c;
} lsnif_section_info;

typedef struct lsnif_header_info {
    uint16_t version_major;
    uint16_t version_minor;
    uint32_t section_count;
    uint64_t file_size;
    uint64_t table_offset;
} lsnif_header_info;

/* Parses the header and section table of `data` and checks every section's
 * payload (checksums, decompression) without building a model. Fills at most
 * `capacity` entries of `sections` (may be NULL when capacity is 0) and sets
 * `*count` to the number of sections in the table. Returns the first structural
 * error; per-section payload problems are reported in the entries and as
 * LSNIF_ERR_CHECKSUM / LSNIF_ERR_DECOMPRESS after all entries are filled.
 * NULL: `data` only when size is 0, `sections` only when capacity is 0; `header`,
 * `count` and `error` may be NULL. */
LSNIF_API lsnif_status lsnif_scan_memory(const void* data, size_t size, lsnif_header_info* header,
                                         lsnif_section_info* sections, uint32_t capacity, uint32_t* count,
                                         lsnif_error* error);

/* ---- The model --------------------------------------------------------------- */

typedef struct lsnif_model lsnif_model;

typedef enum lsnif_distance_encoding {
    /* t = t_near + y * (t_far - t_near) over the ray segment clipped to the box */
    LSNIF_DISTANCE_SEGMENT = 0,
    /* t = t_first + y * box_diagonal, t_first = entry of the first occupied voxel */
    LSNIF_DISTANCE_FIRST_ENTRY_DIAGONAL = 1
} lsnif_distance_encoding;

/* How the hash-grid features are stored (MODL grid_encoding, FORMAT.md §6.2, §6.4). */
typedef enum lsnif_grid_encoding {
    /* IEEE binary16 per feature: the only encoding of 1.0 files */
    LSNIF_GRID_FP16 = 0,
    /* one byte q per feature and per level l a pair (scale_l, offset_l) of f32; the value is
     * fmaf(q, scale_l, offset_l), rounded once (FORMAT.md §6.4.1). Needs version 1.1. */
    LSNIF_GRID_U8_AFFINE = 1
} lsnif_grid_encoding;

/* What the MLP sees of the ray besides the features of its voxel entry points: the bits
 * of MODL ray_inputs (FORMAT.md §6.2, §8; 0 in 1.0 and 1.1 files, where the input is the
 * H * L * F point features only). Inputs follow the point features in bit order. */
typedef enum lsnif_ray_input {
    /* 3 inputs: the ray direction divided by its Euclidean length, object space, x y z */
    LSNIF_RAY_INPUT_DIRECTION = 1,
    /* H inputs: per point slot k, the distance from the first entry point to entry point
     * k over the box diagonal (0 for empty slots) */
    LSNIF_RAY_INPUT_ENTRY_OFFSETS = 2
} lsnif_ray_input;

typedef struct lsnif_info {
    uint16_t version_major;
    uint16_t version_minor;
    uint32_t grid_resolution;    /* V: occupancy grid is V*V*V voxels */
    uint32_t max_points;         /* H: voxel entry points fed to the encoding */
    uint32_t level_count;        /* L */
    uint32_t features_per_level; /* F */
    uint32_t log2_table_size;    /* T = 1 << log2_table_size entries per hashed level */
    uint32_t level_resolution[LSNIF_MAX_LEVELS];
    uint64_t level_entries[LSNIF_MAX_LEVELS]; /* rows actually stored per level */
    uint32_t level_dense[LSNIF_MAX_LEVELS];   /* 1 if the level is indexed densely */
    uint32_t hash_primes[3];
    uint32_t input_width; /* H * L * F plus the ray inputs' (lsnif_get_ray_inputs) */
    uint32_t hidden_layer_count;
    uint32_t hidden_width[LSNIF_MAX_HIDDEN_LAYERS];
    uint32_t output_count; /* 5 + material_count */
    uint32_t material_count;
    uint32_t activation;        /* 0 = ReLU */
    uint32_t distance_encoding; /* lsnif_distance_encoding */
    float box_min[3];           /* object-space bounds the grid spans */
    float box_max[3];
    /* lsnif_grid_encoding (added in 1.1). It sits in what was the 4-byte alignment gap
     * between box_max and parameter_count, so sizeof(lsnif_info) and every other offset
     * are unchanged: programs built against the 1.0 header keep working with this
     * library (they never read the gap), and an older library leaves it zero, which is
     * LSNIF_GRID_FP16, the only encoding it can open. Appending it at the end would have
     * grown the struct and let a newer library write past an older caller's copy. */
    uint32_t grid_encoding;
    uint64_t parameter_count; /* hash-table features + MLP weights and biases */
    uint64_t occupied_voxels;
    uint64_t file_size;
    /* Resident bytes: every byte the handle holds right now (the handle, the feature
     * tables as stored, the occupancy grid at 2 bits per voxel, the network's fp16 weights
     * and what the arithmetic in use adds to them), counted at the size allocated. What a
     * renderer pays to keep the asset open. lsnif_set_arithmetic changes it (fp32 holds
     * the least), and so does the first lsnif_get_array for the occupancy or for a layer,
     * which builds those arrays in the file's layout and keeps them until lsnif_close. */
    uint64_t decoded_bytes;
} lsnif_info;

/* Opens a model from memory. The bytes are copied/decoded: `data` may be freed
 * after the call. Every offset, size, checksum, reserved field and model
 * dimension is verified; on success `*out` must be released with lsnif_close(), on
 * failure `*out` is NULL. NULL: `data` only when size is 0; `error` may be NULL; `out`
 * must not be. */
LSNIF_API lsnif_status lsnif_open_memory(const void* data, size_t size, lsnif_model** out,
                                         lsnif_error* error);
/* Same as lsnif_open_memory for a file path (UTF-8 / native narrow encoding). `path`
 * and `out` must not be NULL; `error` may be. */
LSNIF_API lsnif_status lsnif_open_file(const char* path, lsnif_model** out, lsnif_error* error);
/* Releases a handle. NULL is allowed. */
LSNIF_API void lsnif_close(lsnif_model* model);

/* Fills `*out`. Neither pointer may be NULL. */
LSNIF_API lsnif_status lsnif_get_info(const lsnif_model* model, lsnif_info* out);

/* The model's ray inputs, a bit set of lsnif_ray_input, into `*out` (0 for 1.0 and 1.1
 * files). A function of its own because lsnif_info has no room left for a field without
 * changing its size (see lsnif_info.grid_encoding). Neither pointer may be NULL. Added
 * in 1.2. */
LSNIF_API lsnif_status lsnif_get_ray_inputs(const lsnif_model* model, uint32_t* out);

/* The JSON metadata (UTF-8, not NUL-counted in *length, but NUL-terminated). `length`
 * may be NULL; a NULL model returns NULL and sets *length to 0. */
LSNIF_API const char* lsnif_metadata(const lsnif_model* model, size_t* length);

/* ---- Raw arrays for GPU upload ----------------------------------------------- */

typedef enum lsnif_array_kind {
    LSNIF_ARRAY_OCCUPANCY = 0, /* bits; index 0 only */
    /* [entries][F]; index = level. dtype FLOAT16 for an fp16 grid, UINT8 (the raw bytes q)
     * for a quantized one: dequantize with LSNIF_ARRAY_GRID_DEQUANT of the same level. */
    LSNIF_ARRAY_GRID_LEVEL = 1,
    LSNIF_ARRAY_LAYER_WEIGHTS = 2, /* fp16 [out][in] row-major; index = layer */
    LSNIF_ARRAY_LAYER_BIAS = 3,    /* fp16 [out]; index = layer */
    /* FLOAT32 [2] = {scale, offset} of level `index` of a quantized grid: feature value =
     * fmaf(q, scale, offset), one rounding (FORMAT.md §6.4.1). LSNIF_ERR_INVALID_ARGUMENT
     * for an fp16 grid (check lsnif_info.grid_encoding). Added in 1.1. */
    LSNIF_ARRAY_GRID_DEQUANT = 4
} lsnif_array_kind;

typedef enum lsnif_dtype {
    LSNIF_DTYPE_BITS = 0,    /* packed bits, LSB first, voxel x + V*(y + V*z) */
    LSNIF_DTYPE_FLOAT16 = 1, /* IEEE 754 binary16, little-endian */
    LSNIF_DTYPE_UINT8 = 2,   /* unsigned bytes (quantized grid features; added in 1.1) */
    LSNIF_DTYPE_FLOAT32 = 3  /* IEEE 754 binary32, host order (dequantization pairs; added in 1.1) */
} lsnif_dtype;

typedef struct lsnif_array {
    const void* data; /* owned by the model handle */
    uint64_t bytes;
    uint32_t dtype;   /* lsnif_dtype */
    uint32_t rank;    /* number of valid entries in dims */
    uint64_t dims[3]; /* outermost first: [rows][cols] or [entries][features] or [V][V][V] (z,y,x) */
} lsnif_array;

/* Number of MLP layers (hidden layers + output layer); 0 for a NULL model. */
LSNIF_API uint32_t lsnif_layer_count(const lsnif_model* model);
/* One raw array (see lsnif_array_kind for `index`), owned by the handle and valid until
 * lsnif_close. The feature tables are the ones inference reads; the occupancy bits and
 * the layers' weights and biases are built in the file's layout by the first call that
 * asks for one of them (exactly the stored values; safe from any number of threads) and
 * held from then on (lsnif_info.decoded_bytes counts them). Neither pointer may be NULL;
 * an index out of range returns LSNIF_ERR_INVALID_ARGUMENT. */
LSNIF_API lsnif_status lsnif_get_array(const lsnif_model* model, lsnif_array_kind kind, uint32_t index,
                                       lsnif_array* out);

/* ---- Intersection (FORMAT.md §8) ------------------------------------------------ */

/* A ray: points org + t*dir for t in [tmin, tmax]; tmax may be +INFINITY. dir need not
 * be normalized; t is the ray parameter, so hit distance = t * |dir|. */
typedef struct lsnif_ray {
    float org[3];
    float tmin;
    float dir[3];
    float tmax;
} lsnif_ray;

typedef struct lsnif_hit {
    float t;           /* ray parameter of the hit; +INFINITY on a miss */
    float normal[3];   /* unit shading normal (object or world space, as the query) */
    uint32_t hit;      /* 1 hit, 0 miss (also for invalid rays: zero or non-finite dir) */
    uint32_t material; /* index of the most likely material; 0 without materials */
} lsnif_hit;

/* Intersects `count` object-space rays. Rays that cross no occupied voxel are misses
 * without inference. Runs on the calling thread; concurrent calls on the same model
 * are safe (renderers parallelize across batches). Batches of >= 256 rays amortize
 * the network evaluation best, and rays leaving one point (a shading point's shadow and
 * ambient-occlusion rays) cost less when they follow each other in the batch: they share
 * their first feature point's encoding (same results in any order). `model` must not be
 * NULL; `rays` and `hits` may be NULL only when count is 0. */
LSNIF_API lsnif_status lsnif_intersect(const lsnif_model* model, const lsnif_ray* rays, size_t count,
                                       lsnif_hit* hits);

/* Same for world-space rays against an instance placed by `object_to_world`, a 3x4
 * row-major affine matrix [A | b] (x_world = A x_object + b). Returned t is the world
 * ray's parameter (affine maps preserve it) and the normal is transformed by A^-T.
 * Returns LSNIF_ERR_INVALID_ARGUMENT for a singular or non-finite matrix. NULL rules
 * as lsnif_intersect; `object_to_world` must not be NULL. */
LSNIF_API lsnif_status lsnif_intersect_instance(const lsnif_model* model, const float object_to_world[12],
                                                const lsnif_ray* rays, size_t count, lsnif_hit* hits);

/* Any-hit queries (shadow and ambient-occlusion rays): occluded[i] = 1 when ray i hits the
 * object within [tmin, tmax], else 0 — the decision lsnif_intersect reports as `hit`, bit
 * for bit, without computing the hit's distance, normal and material. Same rules as
 * lsnif_intersect and lsnif_intersect_instance; `occluded` may be NULL only when count is 0. */
LSNIF_API lsnif_status lsnif_occluded(const lsnif_model* model, const lsnif_ray* rays, size_t count,
                                      uint8_t* occluded);
LSNIF_API lsnif_status lsnif_occluded_instance(const lsnif_model* model, const float object_to_world[12],
                                               const lsnif_ray* rays, size_t count, uint8_t* occluded);

/* ---- The escape rule ----------------------------------------------------------------- */

/* Sets the escape rule of later lsnif_intersect* and lsnif_occluded* calls on `model`: a ray
 * whose segment starts inside an occupied voxel (its tmin point lies in the first occupied
 * voxel it meets), that meets at most `max_points` occupied voxels, that one included, and
 * whose occupied voxels are one run in which each shares a face with the one before it (no
 * empty voxel between them), is a miss without evaluating the network. 0, what
 * lsnif_open_* set, turns it off: every ray is answered as FORMAT.md §8 specifies. Meant for
 * rays that leave the asset's own surface (shadow, ambient-occlusion and reflection rays
 * from a point the asset returned): up to its tmax such a ray meets only the voxels around
 * the surface it leaves, and on solid objects the network answers nearly all of them
 * "miss" anyway; skipping it for them saves much of a render's time. On objects of thin
 * parts a voxel or two apart it loses real occluders. A ray entering the grid from outside
 * never escapes.
 * docs/model.md "The escape rule" gives the measurements and the trade-off. `max_points` at
 * most the model's entry points per ray (lsnif_info's max_points), else
 * LSNIF_ERR_INVALID_ARGUMENT; `model` must not be NULL. Must not run concurrently with
 * intersections on the same model. */
LSNIF_API lsnif_status lsnif_set_escape_points(lsnif_model* model, uint32_t max_points);
/* The escape rule's limit in use (0: off); 0 for a NULL model. */
LSNIF_API uint32_t lsnif_get_escape_points(const lsnif_model* model);

/* ---- The enclosed rule --------------------------------------------------------------- */

/* Turns the enclosed rule of later lsnif_occluded* calls on `model` on (`on` nonzero) or off
 * (0, what lsnif_open_* set: every ray is answered as FORMAT.md §8 specifies). The enclosed
 * voxels are the empty voxels of the occupancy grid that no path of empty face neighbours
 * joins to the grid's boundary: the space a closed shell of occupied voxels shuts in (the
 * rule reads them per 2x2x2 block of voxels: an empty voxel counts where every empty voxel
 * of its block is enclosed). A ray that, within [tmin, tmax] and before its H-th occupied
 * voxel, crosses from an occupied voxel into an enclosed one (and met none before its first
 * occupied voxel) has crossed the shell into the inside of the surface, and is answered
 * occluded without evaluating the network (lsnif_intersect* are not affected: they need
 * the hit's distance). On closed surfaces this answers truly what the network sometimes
 * misses, and saves its evaluation; space that voxels of nearby parts close off from the
 * outside without a surface around it is answered occluded too, and so is a ray that starts
 * just inside the surface (leaving its back side into the solid) and ends before leaving
 * the solid: the rule is meant for occlusion rays that leave a surface on the side it is
 * seen from, and for rays from elsewhere. It applies before the escape rule: a ray both
 * would take is occluded. docs/model.md "The enclosed rule" gives the measurements.
 * Turning it on marks spare bits of the occupancy grid (no memory is kept; the call needs
 * V^3 / 8 bytes while it runs and may return LSNIF_ERR_OUT_OF_MEMORY); `model` must not be
 * NULL. Must not run concurrently with intersections on the same model. */
LSNIF_API lsnif_status lsnif_set_enclosed_rule(lsnif_model* model, int on);
/* Whether the enclosed rule is on (1) or off (0); 0 for a NULL model. */
LSNIF_API int lsnif_get_enclosed_rule(const lsnif_model* model);

/* ---- Arithmetic of the network --------------------------------------------------- */

typedef enum lsnif_arithmetic {
    /* The fastest of INT8, BF16 and FP32 the CPU supports. What lsnif_open_* choose. */
    LSNIF_ARITHMETIC_AUTO = 0,
    /* The reference of FORMAT.md §8: every product in fp32. Same results on every machine
     * (fused multiply-adds in one order on every CPU: docs/pipeline.md). */
    LSNIF_ARITHMETIC_FP32 = 1,
    /* Hidden layers with bfloat16 operands and fp32 accumulation (AVX-512 BF16); bias,
     * ReLU and the output layer in fp32. Faster; hit decisions agree with FP32 on >= 99.5 %
     * of rays. Falls back to FP32 on CPUs without AVX-512 BF16. */
    LSNIF_ARITHMETIC_BF16 = 2,
    /* Hidden layers with 8-bit operands (each row of a layer's input and each column of its
     * weights quantized with its own scale) summed exactly in int32 (AVX-512 VNNI); bias,
     * ReLU and the output layer in fp32. Fastest; hit decisions agree with FP32 on >= 99.5 %
     * of rays. Falls back to BF16, then FP32, on CPUs without AVX-512 VNNI. */
    LSNIF_ARITHMETIC_INT8 = 3
} lsnif_arithmetic;

/* Sets the arithmetic later lsnif_intersect* calls on `model` use and writes the one in
 * use (after any fallback) to `*in_use` (may be NULL). Must not run concurrently with
 * intersections on the same model. `model` must not be NULL; an unknown `requested` is
 * LSNIF_ERR_INVALID_ARGUMENT. */
LSNIF_API lsnif_status lsnif_set_arithmetic(lsnif_model* model, lsnif_arithmetic requested,
                                            lsnif_arithmetic* in_use);
/* The arithmetic in use (FP32, BF16 or INT8); LSNIF_ARITHMETIC_FP32 for a NULL model. */
LSNIF_API lsnif_arithmetic lsnif_get_arithmetic(const lsnif_model* model);
/* "auto", "fp32", "bf16" or "int8" (static storage); "unknown" for any other value. */
LSNIF_API const char* lsnif_arithmetic_string(lsnif_arithmetic arithmetic);

#ifdef __cplusplus
}
#endif

#endif /* LSNIF_LSNIF_H */
