// Trainer: gradient checks, Adam against a scalar reference, agreement with the reader's
// forward pass, determinism, divergence guard, and learning an analytic scene end to end.
#include <doctest/doctest.h>

#include "amx.hpp"  // detail::bf16_backend(): skip the bf16 runs without a bf16 backend

#include <lsnif/analytic/spheres.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/trainer/adam.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <memory>

using namespace lsnif;
using namespace lsnif::trainer;
using namespace lsnif::analytic;
using namespace lsnif::samples;

namespace {

format::ModelDesc small_desc() {
    format::ModelDesc d;
    d.grid_resolution = 8;
    d.max_points = 4;
    d.level_resolution = {8, 16};  // 16: hashed at T = 2^10; 8: dense (729 <= 1024)
    d.features_per_level = 2;
    d.log2_table_size = 10;
    d.hidden_width = {16, 12};
    d.material_count = 3;
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    return d;
}

SpheresSource two_spheres(const format::ModelDesc& d) {
    return SpheresSource({{{-0.35f, 0.1f, 0.0f}, 0.4f}, {{0.4f, -0.2f, 0.1f}, 0.3f}}, d.box_min, d.box_max);
}

}  // namespace

TEST_CASE("Adam matches a scalar reference step for step, with per-row step counters") {
    const AdamConfig c{0.05f, 0.9f, 0.99f, 1e-8f, 0.01f};
    float p[2] = {1.0f, -2.0f}, m[2] = {0, 0}, v[2] = {0, 0};
    double rp[2] = {1.0, -2.0}, rm[2] = {0, 0}, rv[2] = {0, 0};
    int row_t[2] = {0, 0};
    for (int step = 1; step <= 50; ++step) {
        for (int i = 0; i < 2; ++i) {
            // Row 1 only receives gradient every third step (a sparse hash row).
            if (i == 1 && step % 3) continue;
            const float g = float(std::sin(step * 0.7 + i)) * 3.0f;
            adam_update(&p[i], &m[i], &v[i], &g, 1, std::uint32_t(++row_t[i]), c.lr, 1.0f, c);
            // Reference, Kingma & Ba Algorithm 1 with explicit bias-corrected moments.
            const double gi = double(g) + c.l2 * rp[i];
            rm[i] = c.beta1 * rm[i] + (1 - c.beta1) * gi;
            rv[i] = c.beta2 * rv[i] + (1 - c.beta2) * gi * gi;
            const double mhat = rm[i] / (1 - std::pow(double(c.beta1), row_t[i]));
            const double vhat = rv[i] / (1 - std::pow(double(c.beta2), row_t[i]));
            // Folding the correction into the step size moves eps by sqrt(1-b2^t): same
            // update up to that (documented in adam.hpp); eps is tiny here.
            rp[i] -= c.lr * mhat / (std::sqrt(vhat) + c.eps);
            REQUIRE(p[i] == doctest::Approx(rp[i]).epsilon(1e-4));
        }
    }
    CHECK(row_t[1] == 16);
    // Gradient scaling (clipping) scales g before the moments.
    float q = 1, qm = 0, qv = 0, g = 4, q2 = 1, qm2 = 0, qv2 = 0, g2 = 2;
    adam_update(&q, &qm, &qv, &g, 1, 1, 0.1f, 0.5f, {0.1f, 0.9f, 0.99f, 0.0f, 0.0f});
    adam_update(&q2, &qm2, &qv2, &g2, 1, 1, 0.1f, 1.0f, {0.1f, 0.9f, 0.99f, 0.0f, 0.0f});
    CHECK(qm == qm2);
}

TEST_CASE(
    "sparse row update equals the per-row Adam step and zeroes the gradients it used; inactive rows keep "
    "their state") {
    const AdamConfig c{0.02f, 0.9f, 0.99f, 1e-10f, 0.0f};
    const std::uint32_t F = 3;
    const std::size_t rows = 203;  // ragged against the 32-row blocks
    std::vector<double> correction(64);
    for (std::uint32_t t = 1; t < correction.size(); ++t) correction[t] = adam_bias_correction(c, t);
    std::vector<float> p(rows * F), m(rows * F), v(rows * F), g(rows * F);
    std::vector<std::uint32_t> row_step(rows, 0);
    for (std::size_t i = 0; i < p.size(); ++i) p[i] = float(std::sin(0.37 * double(i)));
    auto rp = p, rm = m, rv = v;
    auto rsteps = row_step;
    const auto r_active = [](std::size_t r, std::uint32_t step) { return (r * 7 + step) % 5 != 0; };
    for (std::uint32_t step = 1; step <= 40; ++step) {
        std::vector<std::uint8_t> active(rows), expect_active(rows);
        for (std::size_t r = 0; r < rows; ++r) active[r] = std::uint8_t(r_active(r, step));
        for (std::size_t i = 0; i < g.size(); ++i)
            g[i] = active[i / F] ? float(std::cos(0.11 * double(i) + step)) : float(1e30);  // stale garbage
        float want_max = 0;
        for (std::size_t r = 0; r < rows; ++r) {
            if (!active[r]) continue;
            const std::uint32_t t = ++rsteps[r];
            adam_update_corrected(&rp[r * F], &rm[r * F], &rv[r * F], &g[r * F], F,
                                  float(double(c.lr) * correction[t]), 0.5f, c);
        }
        for (const float x : rp) want_max = std::max(want_max, std::fabs(x));  // every row in range
        const SparseRows sr{p.data(), m.data(), v.data(), g.data(), active.data(), row_step.data(), F};
        // Two calls over a split range, as two threads would make them.
        const float got_max = std::max(adam_update_rows(sr, 0, 77, c.lr, correction.data(), 0.5f, c),
                                       adam_update_rows(sr, 77, rows, c.lr, correction.data(), 0.5f, c));
        CHECK(active == expect_active);             // every flag cleared
        for (std::size_t i = 0; i < g.size(); ++i)  // used gradients zeroed, the others untouched
            REQUIRE(g[i] == ((r_active(i / F, step)) ? 0.0f : float(1e30)));
        CHECK(row_step == rsteps);
        CHECK(got_max == doctest::Approx(want_max).epsilon(1e-6));
        for (std::size_t i = 0; i < p.size(); ++i) {
            // Same formula; the compiler may contract it into FMAs differently when it
            // vectorizes, so allow a few ulps.
            REQUIRE(p[i] == doctest::Approx(rp[i]).epsilon(1e-6));
            REQUIRE(m[i] == doctest::Approx(rm[i]).epsilon(1e-5));
            REQUIRE(v[i] == doctest::Approx(rv[i]).epsilon(1e-5));
        }
    }
}

TEST_CASE("finite-difference gradient check for every parameter kind and loss term") {
    const format::ModelDesc d = small_desc();
    SpheresSource src = two_spheres(d);
    // Terms: visibility, distance, normal (cosine), material, normal (chord).
    for (int term = 0; term < 5; ++term) {
        TrainConfig cfg;
        cfg.threads = 2;
        cfg.seed = 3;
        // Exact arithmetic: a 1e-4 step is below bf16 resolution for most weights.
        cfg.mlp_precision = MlpPrecision::fp32;
        // One loss term at a time, so each term's gradient is checked on its own.
        cfg.loss = {term == 0 ? 1.f : 0.f, term == 1 ? 1.f : 0.f, term == 2 || term == 4 ? 1.f : 0.f,
                    term == 3 ? 1.f : 0.f};
        cfg.normal_loss = term == 4 ? NormalLoss::chord : NormalLoss::cosine;
        cfg.huber_delta = 10.0f;  // quadratic regime: smooth for finite differences
        Trainer tr(d, src.occupancy(d), cfg);
        // Larger weights than the init so every parameter carries a measurable gradient.
        for (auto& level : tr.grid())
            for (std::size_t i = 0; i < level.size(); ++i) level[i] = 0.5f * float(std::sin(double(i) * 1.3));
        std::vector<Sample> raw;
        src.generate(11, 600, raw);
        for (std::size_t i = 0; i < raw.size(); ++i) raw[i].material = std::uint32_t(i % 3);
        const auto batch = tr.reachable(raw);
        REQUIRE(batch.size() > 100);
        Gradients g;
        tr.loss_and_gradients(batch, &g);
        auto loss_at = [&]() { return tr.loss_and_gradients(batch, nullptr).total; };
        // Parameters to probe: biases and weights of each layer, and the most-touched
        // rows of each hash level (so the finite difference is well above float noise).
        struct Probe {
            std::vector<float>* p;
            const std::vector<float>* grad;
            std::size_t i;
            const char* kind;
        };
        std::vector<Probe> probes;
        for (std::uint32_t k = 0; k < d.layer_count(); ++k) {
            for (std::size_t i : {std::size_t(0), g.weights[k].size() / 2, g.weights[k].size() - 1})
                probes.push_back({&tr.weights()[k], &g.weights[k], i, "weight"});
            for (std::size_t i = 0; i < g.biases[k].size(); i += 3)
                probes.push_back({&tr.biases()[k], &g.biases[k], i, "bias"});
        }
        for (std::uint32_t l = 0; l < d.level_count(); ++l) {
            std::vector<std::size_t> idx(g.grid[l].size());
            for (std::size_t i = 0; i < idx.size(); ++i) idx[i] = i;
            std::partial_sort(idx.begin(), idx.begin() + 4, idx.end(), [&](std::size_t a, std::size_t b) {
                return std::fabs(g.grid[l][a]) > std::fabs(g.grid[l][b]);
            });
            for (int j = 0; j < 4; ++j) probes.push_back({&tr.grid()[l], &g.grid[l], idx[j], "grid"});
        }
        int checked = 0;
        for (const Probe& pr : probes) {
            const float analytic = (*pr.grad)[pr.i];
            if (term == 3 && std::string(pr.kind) == "grid" && analytic == 0.0f) continue;
            float& x = (*pr.p)[pr.i];
            const float x0 = x;
            const float h = 1e-4f;
            x = x0 + h;
            const double lp = loss_at();
            x = x0 - h;
            const double lm = loss_at();
            x = x0;
            const double numeric = (lp - lm) / (2.0 * h);
            if (std::fabs(numeric) < 1e-5 && std::fabs(analytic) < 1e-5)
                continue;  // inactive (ReLU off / no hit)
            if (std::fabs(numeric - analytic) >
                0.03 * std::max(std::fabs(numeric), std::fabs(double(analytic))) + 2e-5)
                MESSAGE("term " << term << " " << pr.kind << "[" << pr.i << "] analytic " << analytic
                                << " numeric " << numeric);
            INFO("term " << term << " " << pr.kind << "[" << pr.i << "] analytic " << analytic << " numeric "
                         << numeric);
            CHECK(std::fabs(numeric - analytic) <=
                  0.03 * std::max(std::fabs(numeric), std::fabs(double(analytic))) + 2e-5);
            ++checked;
        }
        CHECK(checked >= 10);
    }
}

TEST_CASE("the chord normal loss is sqrt(2 (1 - cos) + eps^2) - eps of the cosine loss, per sample") {
    const format::ModelDesc d = small_desc();
    SpheresSource src = two_spheres(d);
    std::vector<Sample> raw;
    src.generate(5, 400, raw);
    const auto trainer_with = [&](NormalLoss kind) {
        TrainConfig cfg;
        cfg.threads = 1;
        cfg.seed = 9;  // same seed: same weights in both trainers
        cfg.normal_loss = kind;
        cfg.normal_chord_epsilon = 0.05f;
        return std::make_unique<Trainer>(d, src.occupancy(d), cfg);
    };
    const auto cosine_tr = trainer_with(NormalLoss::cosine), chord_tr = trainer_with(NormalLoss::chord);
    int checked = 0;
    for (const Sample& s : cosine_tr->reachable(raw)) {
        if (!s.hit) continue;
        // loss_and_gradients does not update the weights: both trainers stay as initialized.
        // Both add the same hinge, zero where the prediction is in the target's hemisphere;
        // the relation below holds only where it is zero, as for these samples.
        const double cosine = cosine_tr->loss_and_gradients(std::span(&s, 1), nullptr).normal;
        const double chord = chord_tr->loss_and_gradients(std::span(&s, 1), nullptr).normal;
        REQUIRE(cosine > 1e-3);  // an untrained network: a real angle
        CHECK(chord == doctest::Approx(std::sqrt(2 * cosine + 0.05 * 0.05) - 0.05).epsilon(1e-4));
        if (++checked == 20) break;
    }
    CHECK(checked == 20);
}

TEST_CASE("a normal pointing away from its target still gets a gradient toward it, for both loss shapes") {
    // A loss of the angle alone is flat along the output's own direction and its tangential
    // gradient vanishes at the antipode: without the hinge both components below are 0.
    const format::ModelDesc d = small_desc();
    SpheresSource src = two_spheres(d);
    std::vector<Sample> raw;
    src.generate(5, 400, raw);
    for (const NormalLoss kind : {NormalLoss::cosine, NormalLoss::chord}) {
        CAPTURE(int(kind));
        TrainConfig cfg;
        cfg.threads = 1;
        cfg.seed = 9;
        cfg.mlp_precision = MlpPrecision::fp32;
        cfg.normal_loss = kind;
        cfg.loss = {0.f, 0.f, 1.f, 0.f};  // the normal term alone
        Trainer tr(d, src.occupancy(d), cfg);
        const auto batch = tr.reachable(raw);
        const auto hit = std::find_if(batch.begin(), batch.end(), [](const Sample& s) { return s.hit != 0; });
        REQUIRE(hit != batch.end());
        const Sample s = *hit;
        // The output layer answers -t for every input: zero weights, bias -t.
        const std::size_t last = tr.weights().size() - 1;
        std::fill(tr.weights()[last].begin(), tr.weights()[last].end(), 0.0f);
        for (int a = 0; a < 3; ++a) tr.biases()[last][format::OutputLayout::normal + a] = -s.normal[a];
        Gradients g;
        const double loss = tr.loss_and_gradients(std::span(&s, 1), &g).normal;
        CHECK(loss > 1.0);             // the shape's maximum plus the hinge
        double along = 0, across = 0;  // the bias gradient along t, and its size across t
        for (int a = 0; a < 3; ++a) along += g.biases[last][format::OutputLayout::normal + a] * s.normal[a];
        for (int a = 0; a < 3; ++a) {
            const double r = g.biases[last][format::OutputLayout::normal + a] - along * s.normal[a];
            across += r * r;
        }
        // Descent moves the bias along +t (the gradient points along -t), with the hinge's full
        // slope: weight 1 times the one sample.
        CHECK(along == doctest::Approx(-1.0).epsilon(1e-3));
        CHECK(std::sqrt(across) < 1e-3);
    }
}

TEST_CASE("loss and every gradient are the same bit for bit for any thread count, and cleared after use") {
    // The batch is cut into chunks that depend on its size alone, each summed in row order,
    // and the chunks are added in chunk order; every hash row has one owning thread that sums
    // the samples in batch order. So nothing depends on how many threads share the work.
    // small_desc's levels have 729 and 1,024 rows: with 2 threads each owns one level, with 3
    // and 5 every level's rows are split. With three levels (a coarse dense one below the
    // voxel grid, whose points have 8 corners), 2 threads own whole levels dealt by estimated
    // cost. ~900 reachable rays make 3-4 chunks of 256 rows, the last one short.
    format::ModelDesc three = small_desc();
    three.level_resolution = {4, 8, 16};
    for (const format::ModelDesc& d : {small_desc(), three}) {
        CAPTURE(d.level_count());
        SpheresSource src = two_spheres(d);
        std::vector<Sample> raw;
        src.generate(5, 900, raw);
        Gradients want;
        double want_loss = 0;
        for (const std::uint32_t threads : {1u, 2u, 3u, 5u}) {
            CAPTURE(threads);
            TrainConfig cfg;
            cfg.threads = threads;
            cfg.seed = 4;
            cfg.mlp_precision = MlpPrecision::fp32;
            Trainer tr(d, src.occupancy(d), cfg);
            for (auto& level : tr.grid())
                for (std::size_t i = 0; i < level.size(); ++i)
                    level[i] = 0.3f * float(std::cos(double(i) * 0.7));
            const auto batch = tr.reachable(raw);
            Gradients first, second;
            const double loss = tr.loss_and_gradients(batch, &first).total;
            tr.loss_and_gradients(batch, &second);  // nothing left over from the first call
            CHECK(first.grid == second.grid);
            CHECK(first.weights == second.weights);
            CHECK(first.biases == second.biases);
            std::size_t nonzero = 0;
            for (const auto& level : first.grid)
                for (const float x : level) nonzero += x != 0.0f;
            CHECK(nonzero > 500);
            if (want.grid.empty()) want = first, want_loss = loss;
            CHECK(first.grid == want.grid);
            CHECK(first.weights == want.weights);
            CHECK(first.biases == want.biases);
            CHECK(std::memcmp(&loss, &want_loss, sizeof loss) == 0);
        }
    }
}

TEST_CASE("training forward equals the reader's forward bit for bit on exported fp16 weights") {
    const format::ModelDesc d = small_desc();
    SpheresSource src = two_spheres(d);
    TrainConfig cfg;
    cfg.steps = 30;
    cfg.batch_size = 512;
    cfg.threads = 2;
    Trainer tr(d, src.occupancy(d), cfg);
    std::vector<Sample> raw;
    src.generate(5, 3000, raw);
    const auto train = tr.reachable(raw);
    tr.train(train);
    tr.round_to_fp16();
    const auto model = tr.export_model("{}");
    const format::Runtime rt = format::make_runtime(model);
    const auto mine = tr.predict_raw(train);
    // Reader side: same encode + MLP from format/, on the decoded fp16 file contents.
    const auto grid = rt.grid_views();
    std::vector<float> row(rt.geo.input_width), scratch;
    format::RayPoints pts;
    const std::uint32_t outs = d.output_count();
    for (std::size_t i = 0; i < train.size(); ++i) {
        REQUIRE(format::trace_points(rt.geo, rt.occupancy, train[i].ray, pts) == format::TraceStatus::ok);
        format::encode_points(rt.geo, grid.data(), pts, row.data());
        const float* out = format::mlp_forward(rt.net, row.data(), 1, scratch);
        REQUIRE(std::memcmp(out, mine.data() + i * outs, outs * sizeof(float)) == 0);
    }
}

TEST_CASE("the same seed gives identical weights for any thread count; the guard survives an absurd rate") {
    const format::ModelDesc d = small_desc();
    SpheresSource src = two_spheres(d);
    std::vector<Sample> raw;
    src.generate(9, 4000, raw);
    // Both MLP precisions (bf16 falls back to fp32 without a bf16 backend, which is then
    // checked twice). A batch of 1,300 rows: five chunks of 256 and a short one.
    for (const MlpPrecision precision : {MlpPrecision::fp32, MlpPrecision::bf16}) {
        CAPTURE(precision_name(precision));
        auto run = [&](std::uint64_t seed, std::uint32_t threads) {
            TrainConfig cfg;
            cfg.steps = 40;
            cfg.batch_size = 1300;
            cfg.threads = threads;
            cfg.seed = seed;
            cfg.mlp_precision = precision;
            Trainer tr(d, src.occupancy(d), cfg);
            tr.train(tr.reachable(raw));
            return tr.export_model("{}");
        };
        const auto a = run(1, 2), c = run(2, 2);
        for (const std::uint32_t threads : {1u, 2u, 3u, 5u}) {
            CAPTURE(threads);
            const auto b = run(1, threads);
            CHECK(a.weights == b.weights);
            CHECK(a.grid == b.grid);
            CHECK(a.biases == b.biases);
        }
        CHECK(a.weights != c.weights);
    }

    TrainConfig cfg;
    cfg.steps = 60;
    cfg.batch_size = 1024;
    cfg.threads = 2;
    Trainer tr(d, src.occupancy(d), cfg);
    const auto train = tr.reachable(raw);
    for (int i = 0; i < 25; ++i) tr.step(train);  // healthy start, snapshot taken
    tr.set_lr_scale(1e6f);                        // absurd learning rate: the loss explodes
    const TrainResult r = tr.train(train);
    CHECK(r.rollbacks >= 1);
    CHECK(tr.lr_scale() < 1e6f);
    for (const auto& w : tr.weights())
        for (float x : w) REQUIRE(std::isfinite(x));
    const auto exported = tr.export_model("{}");
    CHECK_FALSE(format::validate_model(exported));  // finite, writable
}

namespace {

void learn_spheres(MlpPrecision precision) {
    format::ModelDesc d;  // v1 dimensions except a smaller table and MLP: keeps CI fast
    d.grid_resolution = 32;
    d.max_points = 18;
    d.level_resolution = {64, 128};
    d.features_per_level = 3;
    d.log2_table_size = 15;
    d.hidden_width = {64, 64};
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    SpheresSource src(
        {{{-0.35f, 0.1f, 0.0f}, 0.4f}, {{0.4f, -0.2f, 0.1f}, 0.3f}, {{0.1f, 0.55f, -0.3f}, 0.2f}}, d.box_min,
        d.box_max);
    TrainConfig cfg;
    cfg.steps = 1200;
    cfg.batch_size = 4096;
    cfg.threads = 2;
    cfg.mlp_precision = precision;
    Trainer tr(d, src.occupancy(d), cfg);
    MESSAGE("MLP precision " << std::string(precision_name(tr.mlp_precision())));
    std::vector<Sample> raw, held;
    src.generate(100, 300000, raw);
    src.generate(200, 30000, held);  // different seed: held-out rays
    const auto train = tr.reachable(raw);
    const TrainResult r = tr.train(train);
    REQUIRE_FALSE(r.diverged);
    const format::Runtime rt = format::make_runtime(tr.export_model("{}"));
    const Metrics m = held_out_metrics(rt, held, 2);
    for (int f = 0; f < kFamilyCount; ++f) {
        const FamilyMetrics& fm = m.family[f];
        MESSAGE(std::string(family_name(Family(f)))
                << ": rays " << fm.rays << " vis " << fm.visibility_accuracy << " dist med "
                << fm.distance_median_pct << "% p95 " << fm.distance_p95_pct << "% normal med "
                << fm.normal_median_deg << " deg, culled " << fm.culled_fraction);
        CHECK(fm.culled_true_hits == 0);  // conservative occupancy never culls a true hit
        CHECK(fm.rays > 1000);
    }
    MESSAGE("pooled: vis " << m.pooled.visibility_accuracy << " dist med " << m.pooled.distance_median_pct
                           << "% normal med " << m.pooled.normal_median_deg << " deg, train " << r.seconds
                           << " s");
    // Measured at this budget: 99.87%, 0.65%, 11.4 deg; asserted with margin.
    CHECK(m.pooled.visibility_accuracy >= 0.99);
    CHECK(m.pooled.distance_median_pct <= 1.0);
    CHECK(m.pooled.normal_median_deg <= 14.0);
    for (int f = 0; f < kFamilyCount; ++f) CHECK(m.family[f].visibility_accuracy >= 0.98);
}

}  // namespace

TEST_CASE("learns two spheres end to end: held-out accuracy per family") {
    learn_spheres(MlpPrecision::fp32);
}

// Same budget and thresholds with the products in bf16 on AMX or AVX-512 BF16 (the model
// is still exported and evaluated in fp32/fp16 by the reader). CTest runs it only on CPUs
// with bf16 products and reports it skipped elsewhere (tests/CMakeLists.txt).
TEST_CASE("learns two spheres end to end with bf16 products") {
    REQUIRE_MESSAGE(detail::bf16_backend() != detail::Bf16Backend::none,
                    "no bf16 backend (AMX or AVX-512 BF16)");
    learn_spheres(MlpPrecision::bf16);
}
