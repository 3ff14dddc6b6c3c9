// Definition of the opaque C handle. Internal to format/.
#pragma once

#include <lsnif/format/container.hpp>

struct lsnif_model {
    lsnif::format::ModelData data;
    std::uint64_t file_size = 0;
};
