// The C API of <lsnif/lsnif.h>: thin wrappers over the C++ reader. Nothing may throw
// out of these functions, so each body runs inside a catch-all.
#include <lsnif/base/affine.hpp>
#include <lsnif/format/container.hpp>

#include "heap_bytes.hpp"
#include "model_impl.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <new>

using lsnif::format::Error;

namespace {

void fill_error(lsnif_error* out, const Error& e) {
    if (!out) return;
    out->status = e.status;
    out->reserved = 0;
    out->offset = e.offset;
    const std::size_t n = std::min(e.message.size(), sizeof out->message - 1);
    std::memcpy(out->message, e.message.data(), n);
    out->message[n] = '\0';
}

lsnif_status fail(lsnif_error* out, lsnif_status status, const char* message) {
    fill_error(out, Error{status, UINT64_MAX, message});
    return status;
}

template <class F>
lsnif_status guarded(lsnif_error* err, F&& f) {
    try {
        return f();
    } catch (const std::bad_alloc&) {
        return fail(err, LSNIF_ERR_OUT_OF_MEMORY, "out of memory");
    } catch (...) {
        return fail(err, LSNIF_ERR_INTERNAL, "internal error");
    }
}

// Every byte the handle holds: the handle itself and each array it owns, at its allocated
// size (tests/format/test_resident.cpp counts the allocations), with the file-layout arrays
// lsnif_get_array has built so far.
std::uint64_t resident_bytes(const lsnif_model& model) {
    using lsnif::format::detail::heap_bytes;
    const auto& m = model.data;
    std::uint64_t n =
        sizeof(lsnif_model) + heap_bytes(m.desc.level_resolution) + heap_bytes(m.desc.hidden_width) +
        heap_bytes(m.metadata_json) + heap_bytes(m.occupancy) + heap_bytes(m.grid) + heap_bytes(m.grid_u8) +
        heap_bytes(m.grid_affine) + heap_bytes(m.weights) + heap_bytes(m.biases) + model.runtime.heap_bytes();
    const FileLayoutArrays& f = model.file_arrays;
    if (f.occupancy_ready.load(std::memory_order_acquire)) n += heap_bytes(f.occupancy);
    if (f.network_ready.load(std::memory_order_acquire)) n += heap_bytes(f.weights) + heap_bytes(f.biases);
    return n;
}

const std::vector<std::uint8_t>& file_occupancy(const lsnif_model& model) {
    FileLayoutArrays& f = model.file_arrays;
    std::call_once(f.occupancy_once, [&] {
        f.occupancy = model.runtime.occupancy.voxel_bits();
        f.occupancy_ready.store(true, std::memory_order_release);
    });
    return f.occupancy;
}

const FileLayoutArrays& file_network(const lsnif_model& model) {
    FileLayoutArrays& f = model.file_arrays;
    std::call_once(f.network_once, [&] {
        const auto& net = model.runtime.net;
        for (std::size_t k = 0; k < net.layer_count(); ++k) {
            f.weights.push_back(lsnif::format::model_layer_weights(net, k));
            f.biases.push_back(lsnif::format::model_layer_bias(net, k));
        }
        f.network_ready.store(true, std::memory_order_release);
    });
    return f;
}

lsnif_status open_bytes(std::span<const std::uint8_t> bytes, lsnif_model** out, lsnif_error* error) {
    auto m = lsnif::format::read_model(bytes);
    if (!m) {
        fill_error(error, m.error());
        return m.error().status;
    }
    auto* model = new (std::nothrow) lsnif_model{};
    if (!model) return fail(error, LSNIF_ERR_OUT_OF_MEMORY, "out of memory");
    model->file_size = bytes.size();
    // The runtime takes the arrays; the handle keeps the descriptor and the metadata.
    model->runtime = lsnif::format::make_runtime(std::move(m.value()), lsnif::format::best_mlp_arithmetic());
    model->data = std::move(m.value());
    *out = model;
    fill_error(error, Error{});
    return LSNIF_OK;
}

}  // namespace

namespace lsnif::format {

std::uint64_t resident_bytes(const ModelData& model) {
    lsnif_model handle;
    handle.data = model;
    handle.runtime = make_runtime(std::move(handle.data), MlpArithmetic::fp32);
    return ::resident_bytes(handle);
}

}  // namespace lsnif::format

extern "C" {

const char* lsnif_status_string(lsnif_status status) {
    switch (status) {
        case LSNIF_OK: return "ok";
        case LSNIF_ERR_INVALID_ARGUMENT: return "invalid argument";
        case LSNIF_ERR_IO: return "i/o error";
        case LSNIF_ERR_NOT_LSNIF: return "not an lsnif file";
        case LSNIF_ERR_TRANSFER_DAMAGE: return "damaged in transfer";
        case LSNIF_ERR_TRUNCATED: return "truncated";
        case LSNIF_ERR_VERSION_NEWER: return "written by a newer lsnif; upgrade";
        case LSNIF_ERR_VERSION_OLDER: return "written by an older lsnif; re-convert";
        case LSNIF_ERR_CHECKSUM: return "checksum mismatch";
        case LSNIF_ERR_RESERVED: return "reserved field not zero";
        case LSNIF_ERR_LIMIT: return "size limit exceeded";
        case LSNIF_ERR_LAYOUT: return "invalid layout";
        case LSNIF_ERR_MISSING_SECTION: return "missing required section";
        case LSNIF_ERR_UNKNOWN_REQUIRED: return "unknown required section";
        case LSNIF_ERR_DECOMPRESS: return "decompression failed";
        case LSNIF_ERR_MODEL: return "invalid model";
        case LSNIF_ERR_NONFINITE: return "non-finite value";
        case LSNIF_ERR_OUT_OF_MEMORY: return "out of memory";
        case LSNIF_ERR_INTERNAL: return "internal error";
    }
    return "unknown status";
}

const char* lsnif_version(uint32_t* container_major, uint32_t* container_minor) {
    if (container_major) *container_major = LSNIF_VERSION_MAJOR;
    if (container_minor) *container_minor = LSNIF_VERSION_MINOR;
    return LSNIF_LIBRARY_VERSION;
}

lsnif_status lsnif_scan_memory(const void* data, size_t size, lsnif_header_info* header,
                               lsnif_section_info* sections, uint32_t capacity, uint32_t* count,
                               lsnif_error* error) {
    if ((!data && size) || (!sections && capacity))
        return fail(error, LSNIF_ERR_INVALID_ARGUMENT, "null data or sections pointer");
    return guarded(error, [&] {
        auto r = lsnif::format::scan({static_cast<const std::uint8_t*>(data), size});
        if (!r) {
            if (count) *count = 0;
            fill_error(error, r.error());
            return r.error().status;
        }
        if (header) *header = r->header;
        if (count) *count = std::uint32_t(r->sections.size());
        std::copy_n(r->sections.begin(), std::min<std::size_t>(capacity, r->sections.size()), sections);
        fill_error(error, r->first_payload_error);
        return r->first_payload_error.status;
    });
}

lsnif_status lsnif_open_memory(const void* data, size_t size, lsnif_model** out, lsnif_error* error) {
    if (!out || (!data && size)) return fail(error, LSNIF_ERR_INVALID_ARGUMENT, "null argument");
    *out = nullptr;
    return guarded(error, [&] {
        return open_bytes({static_cast<const std::uint8_t*>(data), size}, out, error);
    });
}

lsnif_status lsnif_open_file(const char* path, lsnif_model** out, lsnif_error* error) {
    if (!out || !path) return fail(error, LSNIF_ERR_INVALID_ARGUMENT, "null argument");
    *out = nullptr;
    return guarded(error, [&] {
        auto bytes = lsnif::format::read_file_bytes(path);
        if (!bytes) {
            fill_error(error, bytes.error());
            return bytes.error().status;
        }
        return open_bytes(bytes.value(), out, error);
    });
}

void lsnif_close(lsnif_model* model) {
    delete model;
}

lsnif_status lsnif_get_ray_inputs(const lsnif_model* model, std::uint32_t* out) {
    if (!model || !out) return LSNIF_ERR_INVALID_ARGUMENT;
    *out = model->data.desc.ray_inputs;
    return LSNIF_OK;
}

lsnif_status lsnif_get_info(const lsnif_model* model, lsnif_info* out) {
    if (!model || !out) return LSNIF_ERR_INVALID_ARGUMENT;
    const auto& d = model->data.desc;
    lsnif_info info{};
    info.version_major = model->data.version_major;
    info.version_minor = model->data.version_minor;
    info.grid_resolution = d.grid_resolution;
    info.max_points = d.max_points;
    info.level_count = d.level_count();
    info.features_per_level = d.features_per_level;
    info.log2_table_size = d.log2_table_size;
    for (std::uint32_t l = 0; l < d.level_count(); ++l) {
        info.level_resolution[l] = d.level_resolution[l];
        info.level_entries[l] = d.level_entries(l);
        info.level_dense[l] = d.level_dense(l);
    }
    std::copy(d.hash_primes.begin(), d.hash_primes.end(), info.hash_primes);
    info.input_width = d.input_width();
    info.hidden_layer_count = std::uint32_t(d.hidden_width.size());
    std::copy(d.hidden_width.begin(), d.hidden_width.end(), info.hidden_width);
    info.output_count = d.output_count();
    info.material_count = d.material_count;
    info.activation = d.activation;
    info.distance_encoding = d.distance_encoding;
    std::copy(d.box_min.begin(), d.box_min.end(), info.box_min);
    std::copy(d.box_max.begin(), d.box_max.end(), info.box_max);
    info.grid_encoding = std::uint32_t(d.grid_encoding);
    info.parameter_count = d.parameter_count();
    info.occupied_voxels = model->runtime.occupancy.occupied_voxels();
    info.file_size = model->file_size;
    info.decoded_bytes = resident_bytes(*model);
    *out = info;
    return LSNIF_OK;
}

const char* lsnif_metadata(const lsnif_model* model, size_t* length) {
    if (!model) {
        if (length) *length = 0;
        return nullptr;
    }
    if (length) *length = model->data.metadata_json.size();
    return model->data.metadata_json.c_str();
}

uint32_t lsnif_layer_count(const lsnif_model* model) {
    return model ? model->data.desc.layer_count() : 0;
}

lsnif_status lsnif_get_array(const lsnif_model* model, lsnif_array_kind kind, uint32_t index,
                             lsnif_array* out) {
    if (!model || !out) return LSNIF_ERR_INVALID_ARGUMENT;
    const auto& rt = model->runtime;
    const auto& d = model->data.desc;
    lsnif_array a{};
    switch (kind) {
        case LSNIF_ARRAY_OCCUPANCY:
            if (index != 0) return LSNIF_ERR_INVALID_ARGUMENT;
            a.dtype = LSNIF_DTYPE_BITS;
            a.rank = 3;
            a.dims[0] = a.dims[1] = a.dims[2] = d.grid_resolution;
            break;
        case LSNIF_ARRAY_GRID_LEVEL:
            if (index >= d.level_count()) return LSNIF_ERR_INVALID_ARGUMENT;
            // The runtime's tables: the stored array, then a tail pad outside `bytes`.
            if (d.grid_encoding == lsnif::format::GridEncoding::u8_affine) {
                a.data = rt.grid_u8[index].data();
                a.bytes = d.level_entries(index) * d.features_per_level;
                a.dtype = LSNIF_DTYPE_UINT8;
            } else {
                a.data = rt.grid[index].data();
                a.bytes = d.level_entries(index) * d.features_per_level * 2;
                a.dtype = LSNIF_DTYPE_FLOAT16;
            }
            a.rank = 2;
            a.dims[0] = d.level_entries(index);
            a.dims[1] = d.features_per_level;
            break;
        case LSNIF_ARRAY_GRID_DEQUANT:
            // Only quantized grids have a dequantization pair (FORMAT.md §6.4.1).
            if (index >= d.level_count() || d.grid_encoding != lsnif::format::GridEncoding::u8_affine)
                return LSNIF_ERR_INVALID_ARGUMENT;
            a.data = &rt.grid_affine[index];  // {scale, offset}: LevelAffine is two packed floats
            a.bytes = 2 * sizeof(float);
            a.dtype = LSNIF_DTYPE_FLOAT32;
            a.rank = 1;
            a.dims[0] = 2;
            break;
        case LSNIF_ARRAY_LAYER_WEIGHTS:
        case LSNIF_ARRAY_LAYER_BIAS: {
            if (index >= d.layer_count()) return LSNIF_ERR_INVALID_ARGUMENT;
            const auto [o, i] = d.layer_shape(index);
            a.dtype = LSNIF_DTYPE_FLOAT16;
            a.rank = kind == LSNIF_ARRAY_LAYER_WEIGHTS ? 2 : 1;
            a.dims[0] = o;
            a.dims[1] = kind == LSNIF_ARRAY_LAYER_WEIGHTS ? i : 0;
            break;
        }
        default: return LSNIF_ERR_INVALID_ARGUMENT;
    }
    // The occupancy and the network exist in the file's layouts only once asked for.
    return guarded(nullptr, [&] {
        if (kind == LSNIF_ARRAY_OCCUPANCY) {
            const auto& bits = file_occupancy(*model);
            a.data = bits.data();
            a.bytes = bits.size();
        } else if (kind == LSNIF_ARRAY_LAYER_WEIGHTS || kind == LSNIF_ARRAY_LAYER_BIAS) {
            const FileLayoutArrays& f = file_network(*model);
            const auto& v = kind == LSNIF_ARRAY_LAYER_WEIGHTS ? f.weights[index] : f.biases[index];
            a.data = v.data();
            a.bytes = v.size() * 2;
        }
        *out = a;
        return LSNIF_OK;
    });
}

lsnif_status lsnif_intersect(const lsnif_model* model, const lsnif_ray* rays, size_t count, lsnif_hit* hits) {
    if (!model || (count && (!rays || !hits))) return LSNIF_ERR_INVALID_ARGUMENT;
    return guarded(nullptr, [&] {
        lsnif::format::intersect(model->runtime, {reinterpret_cast<const lsnif::format::Ray*>(rays), count},
                                 {reinterpret_cast<lsnif::format::Hit*>(hits), count});
        return LSNIF_OK;
    });
}

lsnif_status lsnif_occluded(const lsnif_model* model, const lsnif_ray* rays, size_t count,
                            uint8_t* occluded) {
    if (!model || (count && (!rays || !occluded))) return LSNIF_ERR_INVALID_ARGUMENT;
    return guarded(nullptr, [&] {
        lsnif::format::occluded(model->runtime, {reinterpret_cast<const lsnif::format::Ray*>(rays), count},
                                {occluded, count});
        return LSNIF_OK;
    });
}

}  // extern "C"

namespace {

// World-space rays against an instance: each chunk of rays mapped to object space by the
// inverse of `m` (affine maps preserve the ray parameter), then `query(local, n, base, inv)`
// for rays [base, base + n) (inv: the inverse of m's linear part, which maps normals back).
// LSNIF_ERR_INVALID_ARGUMENT for a singular or non-finite matrix.
template <class Query>
lsnif_status for_object_space(const float m[12], const lsnif_ray* rays, size_t count, Query&& query) {
    const auto inverse = lsnif::base::invert_linear(m);  // translation m[3], m[7], m[11]
    if (!inverse) return LSNIF_ERR_INVALID_ARGUMENT;
    const auto& inv = inverse->inv;
    return guarded(nullptr, [&] {
        constexpr std::size_t kChunk = 1024;
        lsnif_ray local[kChunk];
        for (std::size_t base = 0; base < count; base += kChunk) {
            const std::size_t n = std::min(kChunk, count - base);
            for (std::size_t i = 0; i < n; ++i) {
                const lsnif_ray& w = rays[base + i];
                lsnif_ray& o = local[i];
                const double p[3] = {double(w.org[0]) - m[3], double(w.org[1]) - m[7],
                                     double(w.org[2]) - m[11]};
                for (int r = 0; r < 3; ++r) {
                    o.org[r] = float(inv[r][0] * p[0] + inv[r][1] * p[1] + inv[r][2] * p[2]);
                    o.dir[r] = float(inv[r][0] * w.dir[0] + inv[r][1] * w.dir[1] + inv[r][2] * w.dir[2]);
                }
                o.tmin = w.tmin;
                o.tmax = w.tmax;
            }
            query(local, n, base, inv);
        }
        return LSNIF_OK;
    });
}

}  // namespace

extern "C" {

lsnif_status lsnif_intersect_instance(const lsnif_model* model, const float m[12], const lsnif_ray* rays,
                                      size_t count, lsnif_hit* hits) {
    if (!model || !m || (count && (!rays || !hits))) return LSNIF_ERR_INVALID_ARGUMENT;
    return for_object_space(
        m, rays, count, [&](const lsnif_ray* local, std::size_t n, std::size_t base, const auto& inv) {
            lsnif::format::intersect(model->runtime, {reinterpret_cast<const lsnif::format::Ray*>(local), n},
                                     {reinterpret_cast<lsnif::format::Hit*>(hits + base), n});
            for (std::size_t i = 0; i < n; ++i) {
                lsnif_hit& h = hits[base + i];
                if (!h.hit) continue;
                // Normals transform with the inverse transpose: n_w = A^-T n_o.
                double nw[3], len = 0;
                for (int c = 0; c < 3; ++c) {
                    nw[c] = inv[0][c] * h.normal[0] + inv[1][c] * h.normal[1] + inv[2][c] * h.normal[2];
                    len += nw[c] * nw[c];
                }
                len = std::sqrt(len);
                for (int c = 0; c < 3; ++c) h.normal[c] = len > 0 ? float(nw[c] / len) : 0.0f;
            }
        });
}

lsnif_status lsnif_occluded_instance(const lsnif_model* model, const float m[12], const lsnif_ray* rays,
                                     size_t count, uint8_t* occluded) {
    if (!model || !m || (count && (!rays || !occluded))) return LSNIF_ERR_INVALID_ARGUMENT;
    return for_object_space(
        m, rays, count, [&](const lsnif_ray* local, std::size_t n, std::size_t base, const auto&) {
            lsnif::format::occluded(model->runtime, {reinterpret_cast<const lsnif::format::Ray*>(local), n},
                                    {occluded + base, n});
        });
}

lsnif_status lsnif_set_arithmetic(lsnif_model* model, lsnif_arithmetic requested, lsnif_arithmetic* in_use) {
    using lsnif::format::MlpArithmetic;
    if (!model) return LSNIF_ERR_INVALID_ARGUMENT;
    MlpArithmetic want;
    switch (requested) {
        case LSNIF_ARITHMETIC_AUTO: want = lsnif::format::best_mlp_arithmetic(); break;
        case LSNIF_ARITHMETIC_FP32: want = MlpArithmetic::fp32; break;
        case LSNIF_ARITHMETIC_BF16: want = MlpArithmetic::bf16; break;
        case LSNIF_ARITHMETIC_INT8: want = MlpArithmetic::int8; break;
        default: return LSNIF_ERR_INVALID_ARGUMENT;
    }
    return guarded(nullptr, [&] {
        lsnif::format::set_mlp_arithmetic(model->runtime.net, want);
        if (in_use) *in_use = lsnif_get_arithmetic(model);
        return LSNIF_OK;
    });
}

lsnif_status lsnif_set_escape_points(lsnif_model* model, uint32_t max_points) {
    if (!model || max_points > model->runtime.geo.H) return LSNIF_ERR_INVALID_ARGUMENT;
    model->runtime.escape_points = max_points;
    return LSNIF_OK;
}

uint32_t lsnif_get_escape_points(const lsnif_model* model) {
    return model ? model->runtime.escape_points : 0;
}

lsnif_status lsnif_set_enclosed_rule(lsnif_model* model, int on) {
    if (!model) return LSNIF_ERR_INVALID_ARGUMENT;
    if (model->runtime.enclosed_rule == (on != 0)) return LSNIF_OK;
    return guarded(nullptr, [&] {
        lsnif::format::set_enclosed_rule(model->runtime, on != 0);
        return LSNIF_OK;
    });
}

int lsnif_get_enclosed_rule(const lsnif_model* model) {
    return model && model->runtime.enclosed_rule ? 1 : 0;
}

const char* lsnif_arithmetic_string(lsnif_arithmetic arithmetic) {
    switch (arithmetic) {
        case LSNIF_ARITHMETIC_AUTO: return "auto";
        case LSNIF_ARITHMETIC_FP32: return "fp32";
        case LSNIF_ARITHMETIC_BF16: return "bf16";
        case LSNIF_ARITHMETIC_INT8: return "int8";
    }
    return "unknown";
}

lsnif_arithmetic lsnif_get_arithmetic(const lsnif_model* model) {
    using lsnif::format::MlpArithmetic;
    if (!model) return LSNIF_ARITHMETIC_FP32;
    switch (lsnif::format::mlp_arithmetic(model->runtime.net)) {
        case MlpArithmetic::bf16: return LSNIF_ARITHMETIC_BF16;
        case MlpArithmetic::int8: return LSNIF_ARITHMETIC_INT8;
        case MlpArithmetic::fp32: break;
    }
    return LSNIF_ARITHMETIC_FP32;
}

}  // extern "C"

static_assert(sizeof(lsnif::format::LevelAffine) == 2 * sizeof(float) &&
              offsetof(lsnif::format::LevelAffine, offset) == sizeof(float));
// ABI of lsnif_info as of 1.0 (x86-64 / AArch64 LP64): grid_encoding (1.1) fills the
// alignment gap after box_max, so the size and every older field's offset are unchanged.
static_assert(sizeof(void*) != 8 ||
              (sizeof(lsnif_info) == 280 && offsetof(lsnif_info, box_max) == 232 &&
               offsetof(lsnif_info, grid_encoding) == 244 && offsetof(lsnif_info, parameter_count) == 248 &&
               offsetof(lsnif_info, decoded_bytes) == 272));
static_assert(sizeof(lsnif_ray) == sizeof(lsnif::format::Ray) &&
              offsetof(lsnif_ray, dir) == offsetof(lsnif::format::Ray, dir) &&
              offsetof(lsnif_ray, tmax) == offsetof(lsnif::format::Ray, tmax));
static_assert(sizeof(lsnif_hit) == sizeof(lsnif::format::Hit) &&
              offsetof(lsnif_hit, hit) == offsetof(lsnif::format::Hit, hit) &&
              offsetof(lsnif_hit, material) == offsetof(lsnif::format::Hit, material));
