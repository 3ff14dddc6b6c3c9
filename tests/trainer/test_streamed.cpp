// train_streamed: training in rounds of fresh rays from a SampleSource.
#include <doctest/doctest.h>

#include <lsnif/analytic/spheres.hpp>
#include <lsnif/trainer/streamed.hpp>

#include <cstring>
#include <map>

using namespace lsnif;
using namespace lsnif::trainer;
using namespace lsnif::analytic;
using namespace lsnif::samples;

namespace {

format::ModelDesc tiny_desc() {
    format::ModelDesc d;
    d.grid_resolution = 8;
    d.max_points = 4;
    d.level_resolution = {8, 16};
    d.features_per_level = 2;
    d.log2_table_size = 10;
    d.hidden_width = {16, 16};
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    return d;
}

// Counts the draws it hands out, per seed, around the analytic spheres.
class CountingSource final : public SampleSource {
public:
    explicit CountingSource(const format::ModelDesc& d)
        : spheres_({{{0.1f, 0.0f, -0.1f}, 0.5f}}, d.box_min, d.box_max) {}
    void generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out) override {
        draws[seed] += count;
        spheres_.generate(seed, count, out);
    }
    std::vector<std::uint8_t> occupancy(const format::ModelDesc& d) const { return spheres_.occupancy(d); }
    std::map<std::uint64_t, std::size_t> draws;

private:
    SpheresSource spheres_;
};

TrainConfig small_config() {
    TrainConfig cfg;
    cfg.steps = 30;
    cfg.batch_size = 512;
    cfg.threads = 2;
    cfg.seed = 4;
    return cfg;
}

}  // namespace

TEST_CASE("train_streamed draws every round once, trains every step and is deterministic") {
    const format::ModelDesc d = tiny_desc();
    StreamPlan plan;
    plan.total_rays = 5000;
    plan.rays_per_round = 2000;  // rounds of 2000, 2000, 1000
    plan.window_rounds = 2;
    plan.round_seed = [](std::uint64_t r) { return 100 + r; };
    auto run = [&](CountingSource& src) {
        Trainer tr(d, src.occupancy(d), small_config());
        const StreamedResult s = train_streamed(tr, src, plan);
        CHECK(s.rounds == 3);
        CHECK(s.rays_per_round == 2000);
        CHECK(s.rays_drawn == 5000);
        CHECK(s.rays_reaching > 0);
        CHECK(s.rays_reaching <= s.rays_drawn);
        CHECK(s.entry_points >= double(s.rays_reaching));  // each reaching ray has >= 1 point
        CHECK(s.train.steps == 30);
        CHECK(s.train.samples == 30u * 512u);
        CHECK_FALSE(s.train.diverged);
        return tr.export_model("{}");
    };
    CountingSource a(d), b(d);
    const auto ma = run(a), mb = run(b);
    CHECK(a.draws == std::map<std::uint64_t, std::size_t>{{100, 2000}, {101, 2000}, {102, 1000}});
    CHECK(ma.weights == mb.weights);
    CHECK(ma.grid == mb.grid);
}

TEST_CASE("train_streamed never runs more rounds than steps, and clamps a round to the total") {
    const format::ModelDesc d = tiny_desc();
    StreamPlan plan;
    plan.total_rays = 300;
    plan.rays_per_round = 10;  // 30 rounds wanted, only 30 steps... and fewer steps below
    plan.window_rounds = 0;    // taken as 1
    plan.round_seed = [](std::uint64_t r) { return r; };
    CountingSource src(d);
    TrainConfig cfg = small_config();
    cfg.steps = 12;
    Trainer tr(d, src.occupancy(d), cfg);
    const StreamedResult s = train_streamed(tr, src, plan);
    CHECK(s.rounds == 12);
    CHECK(s.rays_drawn == 120);
    CHECK(s.train.steps == 12);

    StreamPlan big = plan;
    big.rays_per_round = 1u << 20;  // larger than the total: one round of 300
    CountingSource src2(d);
    Trainer tr2(d, src2.occupancy(d), cfg);
    const StreamedResult s2 = train_streamed(tr2, src2, big);
    CHECK(s2.rounds == 1);
    CHECK(s2.rays_per_round == 300);
    CHECK(src2.draws == std::map<std::uint64_t, std::size_t>{{0, 300}});
}

TEST_CASE("train_streamed stops when the progress callback says so, and draws no further round") {
    const format::ModelDesc d = tiny_desc();
    StreamPlan plan;
    plan.total_rays = 5000;
    plan.rays_per_round = 1000;  // five rounds of six steps
    plan.window_rounds = 2;
    plan.round_seed = [](std::uint64_t r) { return 100 + r; };
    CountingSource src(d);
    Trainer tr(d, src.occupancy(d), small_config());
    const StreamedResult s = train_streamed(tr, src, plan, [](const Progress& p) { return p.step < 8; });
    CHECK(s.stopped);
    CHECK(tr.step_count() == 8);  // the step that said "stop" is the last one run
    CHECK(s.train.steps == 8);
    CHECK(src.draws == std::map<std::uint64_t, std::size_t>{{100, 1000}, {101, 1000}});

    // A stop asked at a round's last step (step 12 ends round two) is a stop too: no third
    // round is drawn or trained.
    CountingSource edge(d);
    Trainer at_edge(d, edge.occupancy(d), small_config());
    const StreamedResult e =
        train_streamed(at_edge, edge, plan, [](const Progress& p) { return p.step < 12; });
    CHECK(e.stopped);
    CHECK(at_edge.step_count() == 12);
    CHECK(edge.draws == std::map<std::uint64_t, std::size_t>{{100, 1000}, {101, 1000}});

    CountingSource all(d);
    Trainer full(d, all.occupancy(d), small_config());
    CHECK_FALSE(train_streamed(full, all, plan, [](const Progress&) { return true; }).stopped);
    CHECK(full.step_count() == 30);
}

// The window of rounds is built in place: each round's reachable rays are appended after
// the rounds before it, and the oldest round is dropped from the front. Field by field the
// window must hold what preparing the live rounds' rays in one go gives.
TEST_CASE("prepare_append appends a round in sample order; drop_front leaves the later rounds") {
    const format::ModelDesc d = tiny_desc();
    CountingSource src(d);
    const Trainer tr(d, src.occupancy(d), small_config());
    std::vector<Sample> r0, r1, r2;
    src.generate(1, 1500, r0);
    src.generate(2, 1700, r1);
    src.generate(3, 900, r2);
    const auto same = [](const PreparedSet& a, const PreparedSet& b) {
        REQUIRE(a.size() == b.size());
        REQUIRE(a.H == b.H);
        for (std::size_t i = 0; i < a.size(); ++i) {
            REQUIRE(std::memcmp(&a.samples[i], &b.samples[i], sizeof(Sample)) == 0);
            REQUIRE(a.count[i] == b.count[i]);
            REQUIRE(a.t_near[i] == b.t_near[i]);
            REQUIRE(a.t_far[i] == b.t_far[i]);
            REQUIRE(a.t_first[i] == b.t_first[i]);
            for (std::size_t k = 0; k < std::size_t(a.count[i]) * 3; ++k)
                REQUIRE(a.g[i * a.H * 3 + k] == b.g[i * b.H * 3 + k]);
        }
    };
    const auto joined = [&](std::vector<const std::vector<Sample>*> rounds) {
        std::vector<Sample> all;
        for (const auto* r : rounds) all.insert(all.end(), r->begin(), r->end());
        return tr.prepare(all);
    };
    PreparedSet window;
    tr.prepare_append(r0, window);
    const std::size_t n0 = window.size();
    REQUIRE(n0 > 0);
    REQUIRE(n0 < r0.size());  // some rays miss every occupied voxel and are dropped
    tr.prepare_append(r1, window);
    same(window, joined({&r0, &r1}));
    window.drop_front(n0);
    tr.prepare_append(r2, window);
    same(window, joined({&r1, &r2}));
}
