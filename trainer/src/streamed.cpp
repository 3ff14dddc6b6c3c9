// Training in rounds of fresh rays; see streamed.hpp for the contract.
#include <lsnif/base/clock.hpp>
#include <lsnif/trainer/streamed.hpp>

#include <algorithm>
#include <chrono>
#include <deque>
#include <vector>

namespace lsnif::trainer {

namespace {

using Clock = std::chrono::steady_clock;
using base::seconds_since;

// Adds one round's counters; steps, loss and state flags are the latest round's.
void accumulate(TrainResult& total, const TrainResult& part) {
    total.steps = part.steps;
    total.seconds += part.seconds;
    total.samples += part.samples;
    total.rollbacks = part.rollbacks;
    total.final_loss = part.final_loss;
    total.diverged = part.diverged;
    total.stopped = part.stopped;
    if (!part.message.empty()) total.message = part.message;
}

}  // namespace

StreamedResult train_streamed(Trainer& trainer, SampleSource& source, const StreamPlan& plan,
                              const ProgressFn& progress) {
    const std::uint32_t steps = trainer.config().steps;
    const std::uint32_t window = std::max<std::uint32_t>(1, plan.window_rounds);
    StreamedResult out;
    out.rays_per_round = std::max<std::uint64_t>(1, std::min(plan.rays_per_round, plan.total_rays));
    const std::uint64_t chunk = out.rays_per_round;
    out.rounds = std::min<std::uint64_t>((plan.total_rays + chunk - 1) / chunk, steps);

    PreparedSet pool;          // the latest `window` rounds
    std::vector<Sample> rays;  // this round's draw (capacity reused)
    // Room for the whole window up front: a pool that regrows reallocates and copies
    // hundreds of MB, and every fresh page is a page fault.
    pool.reserve(std::size_t(chunk) * window, trainer.desc().max_points);
    std::deque<std::size_t> in_pool;  // prepared sizes of the pooled rounds, oldest first
    for (std::uint64_t r = 0; r < out.rounds && !out.train.diverged; ++r) {
        auto t0 = Clock::now();
        const std::uint64_t n = std::min(chunk, plan.total_rays - r * chunk);
        source.generate(plan.round_seed(r), n, rays);
        out.rays_drawn += n;
        out.generate_seconds += seconds_since(t0);

        t0 = Clock::now();
        // Drop the oldest round before adding this one: the pool never holds more than
        // the window, and its buffers stop growing after the first rounds.
        if (in_pool.size() >= window) {
            pool.drop_front(in_pool.front());
            in_pool.pop_front();
        }
        const std::size_t before = pool.size();
        trainer.prepare_append(rays, pool);
        for (std::size_t i = before; i < pool.size(); ++i) out.entry_points += pool.count[i];
        out.rays_reaching += pool.size() - before;
        in_pool.push_back(pool.size() - before);
        out.prepare_seconds += seconds_since(t0);

        const auto until = std::uint32_t(r + 1 == out.rounds ? steps : steps * (r + 1) / out.rounds);
        accumulate(out.train, trainer.train(pool, progress, until));
        // A stop asked at the round's last step counts too: the step count alone cannot
        // tell it from a round that simply ended.
        if (!out.train.diverged && (out.train.stopped || trainer.step_count() < until)) {
            out.stopped = true;
            break;
        }
    }
    return out;
}

}  // namespace lsnif::trainer
