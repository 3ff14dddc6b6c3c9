// Training on fresh rays in rounds (docs/model.md "Training data in rounds"): the entry
// point that consumes a SampleSource. Round r draws its rays from the source, prepares
// their features, and trains its share of the steps on the latest `window_rounds` rounds,
// so every step sees recent, distinct rays while memory stays bounded by the window.
#pragma once

#include <lsnif/trainer/trainer.hpp>

#include <cstdint>
#include <functional>

namespace lsnif::trainer {

struct StreamPlan {
    std::uint64_t total_rays = 0;      // rays drawn over all rounds (>= 1)
    std::uint64_t rays_per_round = 0;  // rays per round; clamped to [1, total_rays]
    std::uint32_t window_rounds = 2;   // rounds a step samples from (0 is taken as 1)
    // Seed of round r's draw from the source. The caller owns it so that assets keyed by
    // the caller's recipe stay reproducible.
    std::function<std::uint64_t(std::uint64_t round)> round_seed;
};

struct StreamedResult {
    TrainResult train;                 // summed over rounds; steps, loss and flags of the last
    std::uint64_t rays_per_round = 0;  // after clamping
    std::uint64_t rounds = 0;          // min(ceil(total / per round), steps)
    std::uint64_t rays_drawn = 0;      // rays taken from the source
    std::uint64_t rays_reaching = 0;   // of those, rays that cross an occupied voxel
    double entry_points = 0;           // occupied entry points over the reaching rays
    double generate_seconds = 0;       // in source.generate
    double prepare_seconds = 0;        // computing features and maintaining the window
    bool stopped = false;              // the progress callback asked to stop before the last step
};

// Runs trainer.config().steps steps in rounds. Stops early when training diverged beyond
// recovery (result.train.diverged) or when `progress` returns false (result.stopped; no
// further round is drawn). Deterministic for the trainer's seed and
// thread count, the plan and a deterministic source.
StreamedResult train_streamed(Trainer& trainer, SampleSource& source, const StreamPlan& plan,
                              const ProgressFn& progress = {});

}  // namespace lsnif::trainer
