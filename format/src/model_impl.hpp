// Definition of the opaque C handle. Internal to format/.
#pragma once

#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

struct lsnif_model {
    lsnif::format::ModelData data;
    std::uint64_t file_size = 0;
    lsnif::format::Runtime runtime;  // fp32 tables and network, built once at open
};
