// Definition of the opaque C handle. Internal to format/.
#pragma once

#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

#include <atomic>
#include <cstdint>
#include <mutex>
#include <vector>

// lsnif_get_array hands out arrays in the file's layouts; the runtime keeps the occupancy and
// the weights in its own. Those file-layout arrays are built on the first request for one of
// them (any thread; call_once), then held, unchanged, until lsnif_close.
struct FileLayoutArrays {
    std::once_flag occupancy_once, network_once;
    std::atomic<bool> occupancy_ready{false}, network_ready{false};
    std::vector<std::uint8_t> occupancy;
    std::vector<std::vector<std::uint16_t>> weights, biases;
};

struct lsnif_model {
    // The descriptor and the metadata; make_runtime took the arrays out of it.
    lsnif::format::ModelData data;
    std::uint64_t file_size = 0;
    // Built once at open; owns the occupancy, the feature tables and the network.
    lsnif::format::Runtime runtime;
    mutable FileLayoutArrays file_arrays;
};
