// Triage of a mesh: classification, voxelization, the memory rule; and the order, shards and
// memory of a run's candidates (convert_stages.hpp has the contracts).
#include <lsnif/base/clock.hpp>
#include "convert_stages.hpp"

#include <cinttypes>
#include <map>

namespace lsnif::converter {

using nlohmann::json;
using Clock = std::chrono::steady_clock;
using base::seconds_since;
using namespace stages;

namespace stages {

namespace {

// Index-connected components (vertices shared by index), union-find with path halving.
std::size_t count_components(const scene::Mesh& m) {
    std::vector<std::uint32_t> parent(m.vertex_count());
    std::iota(parent.begin(), parent.end(), 0u);
    auto find = [&](std::uint32_t x) {
        while (parent[x] != x) x = parent[x] = parent[parent[x]];
        return x;
    };
    std::vector<std::uint8_t> used(m.vertex_count(), 0);
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const std::uint32_t a = m.indices[3 * t], b = m.indices[3 * t + 1], c = m.indices[3 * t + 2];
        used[a] = used[b] = used[c] = 1;
        parent[find(a)] = find(b);
        parent[find(b)] = find(c);
    }
    std::size_t n = 0;
    for (std::uint32_t v = 0; v < parent.size(); ++v) n += used[v] && find(v) == v;
    return n;
}

double surface_area(const scene::Mesh& m) {
    double area = 0;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const float* p0 = &m.positions[3 * std::size_t(m.indices[3 * t])];
        const float* p1 = &m.positions[3 * std::size_t(m.indices[3 * t + 1])];
        const float* p2 = &m.positions[3 * std::size_t(m.indices[3 * t + 2])];
        const double e1[3] = {double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2]};
        const double e2[3] = {double(p2[0]) - p0[0], double(p2[1]) - p0[1], double(p2[2]) - p0[2]};
        const double c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};
        area += 0.5 * std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    }
    return area;
}

// The resident bytes of an asset of `d` with its grid stored as `encoding`, before training
// (format::resident_bytes of a model of zeros of that shape): exact but for the metadata,
// counted as kMetadataEstimate bytes, and the neurons pruning removes (fewer bytes). Only an
// estimate: the memory rule is checked again on the asset actually chosen.
constexpr std::size_t kMetadataEstimate = 2048;

std::uint64_t resident_estimate(format::ModelDesc d, format::GridEncoding encoding) {
    d.grid_encoding = encoding;
    auto model = format::make_empty_model(d);
    if (!model) return UINT64_MAX;  // a shape the format cannot hold never beats a BVH
    model->metadata_json.assign(kMetadataEstimate, ' ');
    return format::resident_bytes(*model);
}

// The smallest grid encoding the preset may ship.
format::GridEncoding smallest_encoding(const Preset& p) {
    return p.sizing.quantize ? format::GridEncoding::u8_affine : format::GridEncoding::fp16;
}

// The BVH bytes of a mesh that stays BVH, on `yardstick`.
std::optional<std::uint64_t> measure_bvh(const mesh::MeshView& view, BvhYardstick yardstick,
                                         std::string& error) {
    if (yardstick == BvhYardstick::embree) {
        const auto bytes = sampling::measure_bvh_bytes(view, error);
        return bytes ? std::optional<std::uint64_t>(*bytes) : std::nullopt;
    }
    const auto bvh = sampling::measure_compressed_bvh(view, error);
    return bvh ? std::optional<std::uint64_t>(bvh->bytes()) : std::nullopt;
}

}  // namespace

const char* bvh_yardstick_label(BvhYardstick y) {
    return y == BvhYardstick::compressed ? "compressed" : "Embree";
}

std::string range_problem(const mesh::Box& box) {
    double extent = 0, coord = 0;
    for (int a = 0; a < 3; ++a) {
        extent = std::max(extent, double(box.max[a]) - box.min[a]);
        coord = std::max({coord, std::fabs(double(box.min[a])), std::fabs(double(box.max[a]))});
    }
    if (extent >= kMinModelExtent && extent <= kMaxModelExtent && coord <= kMaxModelExtent) return {};
    char why[200];
    std::snprintf(why, sizeof why,
                  "box extent %.3g (coordinates up to %.3g) is outside the range LSNIF models in "
                  "single precision [%g, %g]",
                  extent, coord, kMinModelExtent, kMaxModelExtent);
    return why;
}

std::optional<Candidate> classify(const Run& run, const scene::Mesh& mesh, bool forced_complex,
                                  MeshOutcome& out) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "classify"});
    Candidate c;
    c.forced = forced_complex;
    const ClassifyRule& rule = run.preset.classify;
    c.view = view_of(mesh);
    auto box = voxelize::padded_box(c.view);
    if (!box) {
        out.settle(Decision::not_modelable, "cannot bound the mesh: " + box.error().message);
        return std::nullopt;
    }
    c.box = *box;
    if (std::string why = range_problem(c.box); !why.empty()) {
        out.settle(Decision::not_modelable, why);
        return std::nullopt;
    }
    c.desc = run.preset.model;
    c.desc.box_min = c.box.min;
    c.desc.box_max = c.box.max;
    sampling::SamplingConfig scfg;
    scfg.threads = run.threads;
    std::string serr;
    c.source = sampling::EmbreeSource::create(c.view, c.box, scfg, serr);
    if (!c.source) {
        out.settle(Decision::not_modelable, "Embree could not build the mesh: " + serr);
        return std::nullopt;
    }
    std::string cerr;
    const auto compressed = sampling::measure_compressed_bvh(c.view, cerr);
    if (!compressed) {
        out.settle(Decision::not_modelable, "the compressed BVH could not be measured: " + cerr);
        return std::nullopt;
    }
    c.bvh = {c.source->bvh_bytes(), compressed->bytes()};
    const std::uint64_t bvh = c.bvh.of(rule.yardstick);
    // Size the tables to the mesh (ClassifyRule): halve T while the asset, held in memory,
    // would not beat the BVH. Levels dense at the preset size stay dense (fewer rows than T).
    if (!c.forced)
        while (c.desc.log2_table_size > rule.min_log2_table_size &&
               double(bvh) <
                   rule.min_memory_ratio * double(resident_estimate(c.desc, smallest_encoding(run.preset))))
            --c.desc.log2_table_size;
    const double ext[3] = {double(c.box.max[0]) - c.box.min[0], double(c.box.max[1]) - c.box.min[1],
                           double(c.box.max[2]) - c.box.min[2]};
    const double box_area = 2 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2]);
    MeshStats& stats = out.stats.emplace();
    stats.box_min = c.box.min;
    stats.box_max = c.box.max;
    stats.area_ratio = surface_area(mesh) / box_area;
    stats.components = count_components(mesh);
    stats.closed = c.source->is_closed();
    stats.solid = c.source->rejects_interior();
    stats.log2_table_size = c.desc.log2_table_size;
    stats.bvh = c.bvh;
    stats.resident_estimate = resident_estimate(c.desc, smallest_encoding(run.preset));
    out.timings.add(Stage::classify, seconds_since(t0));
    return c;
}

std::optional<voxelize::Occupancy> voxelize_mesh(const Run& run, const scene::Mesh& mesh, const Candidate& c,
                                                 MeshOutcome& out) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "voxelize"});
    voxelize::Options vopt;
    vopt.threads = run.threads;
    auto occ = voxelize::voxelize(c.view, c.box, c.desc.grid_resolution, vopt);
    if (!occ) {
        out.settle(Decision::voxelization_failed, "voxelization failed: " + occ.error().message);
        return std::nullopt;
    }
    out.stats->occupied_fraction = double(occ->count()) / double(c.desc.voxel_count());
    out.timings.add(Stage::voxelize, seconds_since(t0));
    return std::move(*occ);
}

bool worth_an_lsnif(const Run& run, const scene::Mesh& mesh, const Candidate& c, MeshOutcome& out) {
    const ClassifyRule& rule = run.preset.classify;
    const std::uint64_t bvh = c.bvh.of(rule.yardstick),
                        est = resident_estimate(c.desc, smallest_encoding(run.preset));
    const double ratio = double(bvh) / double(est);
    char why[200];
    std::snprintf(why, sizeof why,
                  "%s BVH %" PRIu64 " bytes vs LSNIF %" PRIu64 " bytes held in memory (%.2fx)",
                  bvh_yardstick_label(rule.yardstick), bvh, est, ratio);
    out.reasons.push_back(why);
    if (!c.forced && ratio < rule.min_memory_ratio) {
        std::snprintf(why, sizeof why, "memory benefit %.2fx below the %.2fx threshold", ratio,
                      rule.min_memory_ratio);
        out.settle(Decision::no_memory_benefit, why);
        return false;
    }
    if (c.forced)
        out.reasons.push_back("forced complex by --complex " + mesh.name);
    else
        out.reasons.push_back(std::to_string(mesh.triangle_count()) + " triangles");
    if (c.desc.log2_table_size != run.preset.model.log2_table_size)
        out.reasons.push_back("hash tables sized to 2^" + std::to_string(c.desc.log2_table_size) +
                              " rows (preset 2^" + std::to_string(run.preset.model.log2_table_size) +
                              ") to beat the BVH's memory");
    return true;
}

std::string memory_rule_failure(const Run& run, const Candidate& c, std::uint64_t resident_bytes) {
    const ClassifyRule& rule = run.preset.classify;
    const double ratio =
        double(c.bvh.of(rule.yardstick)) / double(std::max<std::uint64_t>(1, resident_bytes));
    if (c.forced || ratio >= rule.min_memory_ratio) return {};
    char why[240];
    std::snprintf(why, sizeof why,
                  "the chosen asset (%" PRIu64
                  " bytes held in memory) is only %.2fx smaller than the %s BVH "
                  "(%.2fx needed)",
                  resident_bytes, ratio, bvh_yardstick_label(rule.yardstick), rule.min_memory_ratio);
    return why;
}

// The classification half of triage_mesh: whether the mesh stays BVH whatever happens next
// (p.out settled), else a candidate (p.candidate and p.occupancy set).
bool triage_decision(const Run& run, const scene::Mesh& mesh, Triaged& p) {
    MeshOutcome& out = p.out;
    if (run.forced(run.opt.force_simple, mesh.name)) {
        out.settle(Decision::forced_simple, "forced simple by --simple " + mesh.name);
        return true;
    }
    const ClassifyRule& rule = run.preset.classify;
    const bool forced_complex = run.forced(run.opt.force_complex, mesh.name);
    if (mesh.triangle_count() < rule.min_triangles && !forced_complex) {
        out.settle(Decision::few_triangles, std::to_string(mesh.triangle_count()) + " triangles < " +
                                                std::to_string(rule.min_triangles) +
                                                ": a BVH is small and exact");
        return true;
    }
    p.candidate = classify(run, mesh, forced_complex, out);
    if (!p.candidate) return true;
    p.occupancy = voxelize_mesh(run, mesh, *p.candidate, out);
    return !p.occupancy || !worth_an_lsnif(run, mesh, *p.candidate, out);
}

Triaged triage_mesh(const Run& run, const std::string& source, const scene::Mesh& mesh, MeshOutcome out,
                    std::vector<std::string>& warnings) {
    Triaged p;
    p.mesh = &mesh;
    p.source = source;
    p.out = std::move(out);
    p.decided = triage_decision(run, mesh, p);
    const BvhYardstick yardstick = run.preset.classify.yardstick;
    if (p.candidate && p.candidate->source) {
        p.bvh_bytes = p.candidate->bvh.of(yardstick);
    } else {
        std::string error;
        if (auto bytes = measure_bvh(view_of(mesh), yardstick, error))
            p.bvh_bytes = *bytes;
        else
            warnings.push_back(source + ": mesh '" + mesh.name +
                               "': its BVH could not be measured (counted as 0 bytes): " + error);
    }
    if (!p.decided) {
        p.estimate = resident_estimate(p.candidate->desc, smallest_encoding(run.preset));
    } else {
        p.candidate.reset();  // a mesh that stays BVH needs no Embree scene any more
        p.occupancy.reset();
    }
    return p;
}

// Estimated BVH bytes saved per asset byte: the budget's conversion order.
double saving_per_byte(const Triaged& p) {
    return (double(p.bvh_bytes) - double(p.estimate)) / double(std::max<std::uint64_t>(1, p.estimate));
}

std::vector<std::size_t> conversion_order(const std::vector<Triaged>& triaged, bool budgeted) {
    std::vector<std::size_t> order;
    for (std::size_t i = 0; i < triaged.size(); ++i)
        if (!triaged[i].decided && !triaged[i].leader) order.push_back(i);
    if (budgeted)
        std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
            if (triaged[a].forced() != triaged[b].forced()) return triaged[a].forced();
            return saving_per_byte(triaged[a]) > saving_per_byte(triaged[b]);
        });
    return order;
}

void mark_shared_assets(const Run& run, std::vector<Triaged>& triaged) {
    std::map<std::string, std::size_t> first;  // asset_key -> leader
    for (std::size_t i = 0; i < triaged.size(); ++i) {
        Triaged& p = triaged[i];
        p.triage_reasons = p.out.reasons.size();
        if (p.decided) continue;
        const auto [it, inserted] = first.emplace(asset_key(run, *p.mesh, p.candidate->desc), i);
        if (!inserted) p.leader = it->second;
    }
}

std::uint64_t bytes_after(const Triaged& p) {
    if (p.out.cls() != MeshClass::complex) return p.bvh_bytes;
    if (p.out.asset) return p.out.asset->resident_bytes;
    return p.estimate;  // a dry run's estimate
}

// The constants were measured on the 2-core reference machine (docs/pipeline.md "Shards").
// Training dominates and scales with steps x batch; drawing the rays scales with triangles.
// Integer arithmetic: every shard must compute the same estimate on any machine.
std::uint64_t estimated_cost_ms(const Run& run, const Triaged& p) {
    const std::uint64_t samples = std::uint64_t(run.preset.train.steps) * run.preset.train.batch_size;
    return 4200 + samples * 255 / 100000 + std::uint64_t(p.mesh->triangle_count()) * 18 / 10000;
}

// Longest processing time first (deal_to_shards); equal costs in key order, so the split is
// a function of the inputs and settings alone.
std::vector<std::uint32_t> shard_owners(const Run& run, std::vector<Triaged>& triaged) {
    std::vector<std::uint32_t> owner(triaged.size(), 0);
    if (run.opt.shard_count == 0) return owner;
    struct Job {
        std::uint64_t cost;
        std::string key;
        std::size_t index;
    };
    std::vector<Job> jobs;
    for (std::size_t i = 0; i < triaged.size(); ++i)
        if (!triaged[i].decided && !triaged[i].leader)
            jobs.push_back({estimated_cost_ms(run, triaged[i]), cache_key(run, triaged[i]), i});
    std::sort(jobs.begin(), jobs.end(),
              [](const Job& a, const Job& b) { return a.cost != b.cost ? a.cost > b.cost : a.key < b.key; });
    std::vector<std::uint64_t> costs;
    for (const Job& j : jobs) costs.push_back(j.cost);
    const std::vector<std::uint32_t> shard = deal_to_shards(costs, run.opt.shard_count);
    for (std::size_t k = 0; k < jobs.size(); ++k) owner[jobs[k].index] = shard[k] + 1;
    for (std::size_t i = 0; i < triaged.size(); ++i)
        if (triaged[i].leader) owner[i] = owner[*triaged[i].leader];
    return owner;
}

}  // namespace stages

std::vector<std::uint32_t> deal_to_shards(const std::vector<std::uint64_t>& costs, std::uint32_t count) {
    std::vector<std::uint32_t> shard(costs.size(), 0);
    std::vector<std::uint64_t> load(std::max(1u, count), 0);
    for (std::size_t k = 0; k < costs.size(); ++k) {
        const auto least = std::size_t(std::min_element(load.begin(), load.end()) - load.begin());
        load[least] += costs[k];
        shard[k] = std::uint32_t(least);
    }
    return shard;
}

}  // namespace lsnif::converter
