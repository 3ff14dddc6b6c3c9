// EmbreeSource's construction and accessors. create() is the only place that knows the
// order of the construction stages (declared, with their contracts, in
// sampling_internal.hpp; each lives in the file of its job); this file holds that
// sequence and the small read-only accessors, so the life cycle of an EmbreeSource can
// be read in one place. Ray generation, the inside test and the benchmark live in
// families.cpp, inside.cpp and throughput.cpp.
#include "sampling_internal.hpp"

namespace lsnif::sampling {

EmbreeSource::EmbreeSource(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
EmbreeSource::~EmbreeSource() = default;

std::unique_ptr<EmbreeSource> EmbreeSource::create(const MeshView& mesh, const Box& box,
                                                   const SamplingConfig& cfg, std::string& error) {
    error.clear();
    auto fail = [&](const std::string& msg) {
        error = "sampling: " + msg;
        return std::unique_ptr<EmbreeSource>();
    };
    if (std::string why = validate_input(mesh, box, cfg); !why.empty()) return fail(why);
    auto impl = std::make_unique<Impl>();
    Impl& m = *impl;
    copy_input(m, mesh, box, cfg);
    build_alias_table(m, compute_face_geometry(m));
    analyze_topology(m);
    if (std::string why = build_embree_scene(m); !why.empty()) return fail(why);
    build_triangle_records(m);
    if (m.parity_ready && cfg.classify_resolution > 0) build_classification_grid(m);
    release_construction_data(m);
    return std::unique_ptr<EmbreeSource>(new EmbreeSource(std::move(impl)));
}

bool EmbreeSource::is_closed() const {
    return impl_->closed;
}
bool EmbreeSource::rejects_interior() const {
    return impl_->parity_ready;
}
InsideTest EmbreeSource::inside_test() const {
    return !impl_->parity_ready ? InsideTest::none
           : impl_->oriented    ? InsideTest::first_hit_facing
                                : InsideTest::parity;
}
std::size_t EmbreeSource::cap_triangle_count() const {
    return impl_->caps.size() / 3;
}
std::size_t EmbreeSource::bvh_bytes() const {
    return impl_->bvh;
}
std::size_t EmbreeSource::device_bytes() const {
    return impl_->device_total;
}
std::size_t EmbreeSource::triangle_count() const {
    return impl_->triangles;
}
float EmbreeSource::diagonal() const {
    return float(impl_->diag);
}
void EmbreeSource::set_threads(std::uint32_t threads) {
    impl_->cfg.threads = threads;
}
std::uint32_t EmbreeSource::threads() const {
    return base::resolve_threads(impl_->cfg.threads);
}
const GenerateCounters& EmbreeSource::counters() const {
    return impl_->counters;
}
std::string EmbreeSource::last_error() const {
    return impl_->error_text();
}

std::vector<std::array<float, 3>> geometric_normals(std::span<const SampleExtras> extras) {
    std::vector<std::array<float, 3>> out(extras.size());
    for (std::size_t i = 0; i < extras.size(); ++i) out[i] = extras[i].geometric_normal;
    return out;
}

}  // namespace lsnif::sampling
