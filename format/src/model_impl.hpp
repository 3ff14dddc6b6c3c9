// Definition of the opaque C handle. Internal to format/.
#pragma once

#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

struct lsnif_model {
    lsnif::format::ModelData data;
    std::uint64_t file_size = 0;
    // Built once at open; owns the occupancy and the feature tables, which `data` no longer
    // holds (make_runtime moved them).
    lsnif::format::Runtime runtime;
};
