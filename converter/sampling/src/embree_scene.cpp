// The Embree side of construction: the device (with its error and memory-monitor
// callbacks, which feed last_error(), bvh_bytes() and device_bytes()), the scene flags and
// build quality, the mesh as geometry 0 and the hole caps as geometry 1 (each under its
// own ray mask), and the commit whose allocations are the BVH's size. Everything that
// talks to Embree's construction API lives here, so the rest of the library only traces.
#include "sampling_internal.hpp"

#include <lsnif/format/cpu.hpp>

#include <atomic>
#include <cmath>
#include <cstring>
#include <unordered_map>

namespace lsnif::sampling {

void EmbreeSource::Impl::on_error(void* user, RTCError code, const char* str) {
    auto* self = static_cast<Impl*>(user);
    std::lock_guard lock(self->error_mutex);
    if (!self->errors.empty()) self->errors += "; ";
    self->errors += "embree error " + std::to_string(int(code)) + ": " + (str ? str : "(no message)");
}

// Called before every allocation (bytes > 0, post = false) and after every release
// (bytes < 0, post = true); a refused or failed allocation is undone the same way.
bool EmbreeSource::Impl::on_memory(void* user, ssize_t bytes, bool /*post*/) {
    static_cast<Impl*>(user)->monitor_bytes.fetch_add(std::int64_t(bytes), std::memory_order_relaxed);
    return true;
}

namespace {

// A triangle geometry with Embree-owned copies of the vertices and indices
// (rtcSetNewGeometryBuffer pads them for its vector loads), committed and attached to the
// scene as `id` under `mask`. Returns an error message on failure.
std::string attach_triangles(EmbreeSource::Impl& m, const std::vector<float>& positions,
                             const std::vector<std::uint32_t>& indices, unsigned mask, unsigned id) {
    RTCGeometry geom = rtcNewGeometry(m.device, RTC_GEOMETRY_TYPE_TRIANGLE);
    if (!geom) return "rtcNewGeometry failed: " + m.error_text();
    rtcSetGeometryBuildQuality(geom, RTC_BUILD_QUALITY_HIGH);
    auto* vb = static_cast<float*>(rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                           3 * sizeof(float), positions.size() / 3));
    auto* ib = static_cast<std::uint32_t*>(rtcSetNewGeometryBuffer(
        geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), indices.size() / 3));
    if (!vb || !ib) {
        rtcReleaseGeometry(geom);
        return "embree buffer allocation failed: " + m.error_text();
    }
    std::memcpy(vb, positions.data(), positions.size() * sizeof(float));
    std::memcpy(ib, indices.data(), indices.size() * sizeof(std::uint32_t));
    rtcSetGeometryMask(geom, mask);
    rtcCommitGeometry(geom);
    rtcAttachGeometryByID(m.scene, geom, id);
    rtcReleaseGeometry(geom);
    return {};
}

// Geometry 1: the hole caps, seen by inside-test rays only. It holds only the loop
// vertices, bit-identical to the mesh's, so the shared edges are watertight.
std::string attach_caps(EmbreeSource::Impl& m) {
    std::unordered_map<std::uint32_t, std::uint32_t> local;
    std::vector<std::uint32_t> cap_index(m.caps.size());
    std::vector<float> cap_pos;
    for (std::size_t k = 0; k < m.caps.size(); ++k) {
        auto [it, fresh] = local.try_emplace(m.caps[k], std::uint32_t(local.size()));
        if (fresh)
            for (int a = 0; a < 3; ++a)
                cap_pos.push_back(m.positions[3 * std::size_t(m.caps[k]) + std::size_t(a)]);
        cap_index[k] = it->second;
    }
    return attach_triangles(m, cap_pos, cap_index, kCapMask, kCapGeometry);
}

// Device with the error and memory callbacks, and an empty scene with the flags the
// inside test needs.
std::string new_device_and_scene(EmbreeSource::Impl& m) {
    // One build thread: Embree's multi-threaded builder allocates per-thread blocks, so the
    // BVH's bytes (bvh_bytes(), what manifests and memory budgets report) can change from
    // build to build, and reports must be reproducible. It costs build time on large meshes
    // (docs/investigations/sizing.md), nothing on tracing: rtcIntersect runs on the calling
    // threads whatever the device's thread count.
    const std::string& isa = m.cfg.embree_isa;
    if (isa == "avx2" && !format::detected_cpu_features().avx2_fma)
        return "this CPU has no AVX2 and FMA: conversion pins Embree's ground truth to its AVX2 kernels "
               "(x86-64-v3 is the floor, docs/pipeline.md \"The same bytes everywhere\")";
    m.device = rtcNewDevice(("threads=1" + (isa.empty() ? std::string() : ",isa=" + isa)).c_str());
    if (!m.device)
        return "rtcNewDevice failed (embree error " + std::to_string(int(rtcGetDeviceError(nullptr))) + ")";
    rtcSetDeviceErrorFunction(m.device, &EmbreeSource::Impl::on_error, &m);
    rtcSetDeviceMemoryMonitorFunction(m.device, &EmbreeSource::Impl::on_memory, &m);
    m.scene = rtcNewScene(m.device);
    if (!m.scene) return "rtcNewScene failed: " + m.error_text();
    // Context filters (parity votes) only where parity votes happen: the flag makes every
    // traversal check for one.
    const bool parity_votes = m.parity_ready && !m.oriented;
    rtcSetSceneFlags(m.scene, RTCSceneFlags(RTC_SCENE_FLAG_ROBUST |
                                            (parity_votes ? RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION : 0)));
    rtcSetSceneBuildQuality(m.scene, RTC_BUILD_QUALITY_HIGH);
    return {};
}

// Builds the BVH; the monitor's growth over the commit is the BVH's size, its total the
// device's.
std::string commit_scene(EmbreeSource::Impl& m) {
    const std::int64_t before = m.monitor_bytes.load();
    rtcCommitScene(m.scene);
    const std::int64_t after = m.monitor_bytes.load();
    if (rtcGetDeviceError(m.device) != RTC_ERROR_NONE || !m.error_text().empty())
        return "embree scene build failed: " + m.error_text();
    m.bvh = std::size_t(std::max<std::int64_t>(0, after - before));
    m.device_total = std::size_t(std::max<std::int64_t>(0, after));
    return {};
}

}  // namespace

namespace {

// What rtcBuildBVH's callbacks count. Nodes are allocated from the builder's thread-local
// allocator only so that the builder has pointers to link; nothing is stored in them.
struct NodeCounts {
    std::atomic<std::uint64_t> inner{0}, leaves{0};
};

std::string index_problem(const MeshView& mesh) {
    const std::size_t vertices = mesh.vertex_count();
    for (std::uint32_t i : mesh.indices)
        if (i >= vertices)
            return "sampling: vertex index " + std::to_string(i) + " out of range (" +
                   std::to_string(vertices) + " vertices)";
    return {};
}

}  // namespace

std::string build_embree_scene(EmbreeSource::Impl& m) {
    if (std::string why = new_device_and_scene(m); !why.empty()) return why;
    if (std::string why = attach_triangles(m, m.positions, m.indices, kMeshMask, kMeshGeometry); !why.empty())
        return why;
    if (!m.caps.empty())
        if (std::string why = attach_caps(m); !why.empty()) return why;
    return commit_scene(m);
}

std::optional<std::size_t> measure_bvh_bytes(const MeshView& mesh, std::string& error) {
    if (std::string why = index_problem(mesh); !why.empty()) {
        error = why;
        return std::nullopt;
    }
    if (mesh.triangle_count() == 0) return 0;  // nothing to build
    EmbreeSource::Impl m;
    m.positions.assign(mesh.positions.begin(), mesh.positions.end());
    m.indices.assign(mesh.indices.begin(), mesh.indices.end());
    if (std::string why = build_embree_scene(m); !why.empty()) {
        error = "sampling: " + why;
        return std::nullopt;
    }
    return m.bvh;
}

std::optional<CompressedBvh> measure_compressed_bvh(const MeshView& mesh, std::string& error) {
    if (std::string why = index_problem(mesh); !why.empty()) {
        error = why;
        return std::nullopt;
    }
    if (mesh.triangle_count() == 0) return CompressedBvh{};
    std::vector<RTCBuildPrimitive> prims(mesh.triangle_count());
    for (std::size_t t = 0; t < prims.size(); ++t) {
        float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int c = 0; c < 3; ++c)
            for (int a = 0; a < 3; ++a) {
                const float v = mesh.positions[std::size_t(mesh.indices[t * 3 + c]) * 3 + a];
                lo[a] = std::min(lo[a], v);
                hi[a] = std::max(hi[a], v);
            }
        prims[t] = {lo[0], lo[1], lo[2], 0u, hi[0], hi[1], hi[2], std::uint32_t(t)};
    }
    RTCDevice device = rtcNewDevice("threads=1");
    if (!device) {
        error = "sampling: rtcNewDevice failed (embree error " +
                std::to_string(int(rtcGetDeviceError(nullptr))) + ")";
        return std::nullopt;
    }
    NodeCounts counts;
    RTCBVH bvh = rtcNewBVH(device);
    RTCBuildArguments args = rtcDefaultBuildArguments();
    args.byteSize = sizeof(args);
    args.buildQuality = RTC_BUILD_QUALITY_MEDIUM;
    args.maxBranchingFactor = 8;
    args.maxDepth = 1024;
    args.sahBlockSize = 1;
    args.minLeafSize = 1;
    args.maxLeafSize = 3;
    args.traversalCost = 1.0f;
    args.intersectionCost = 1.0f;
    args.bvh = bvh;
    args.primitives = prims.data();
    args.primitiveCount = prims.size();
    args.primitiveArrayCapacity = prims.size();
    args.userPtr = &counts;
    args.createNode = [](RTCThreadLocalAllocator alloc, unsigned, void* user) -> void* {
        static_cast<NodeCounts*>(user)->inner++;
        return rtcThreadLocalAlloc(alloc, 8, 8);
    };
    args.setNodeChildren = [](void*, void**, unsigned, void*) {};
    args.setNodeBounds = [](void*, const RTCBounds**, unsigned, void*) {};
    args.createLeaf = [](RTCThreadLocalAllocator alloc, const RTCBuildPrimitive*, size_t,
                         void* user) -> void* {
        static_cast<NodeCounts*>(user)->leaves++;
        return rtcThreadLocalAlloc(alloc, 8, 8);
    };
    const bool built = rtcBuildBVH(&args) != nullptr;
    const RTCError code = rtcGetDeviceError(device);
    rtcReleaseBVH(bvh);
    rtcReleaseDevice(device);
    if (!built || code != RTC_ERROR_NONE) {
        error = "sampling: rtcBuildBVH failed (embree error " + std::to_string(int(code)) + ")";
        return std::nullopt;
    }
    return CompressedBvh{counts.inner.load(), counts.leaves.load()};
}

}  // namespace lsnif::sampling
