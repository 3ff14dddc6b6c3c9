// A batch's answers do not depend on how a caller splits it into calls: one ray per call
// (a renderer's single-ray tracing, the Embree user geometry's 1-ray callbacks) takes the
// scalar walk and fewer than 16 rays the layer-by-layer network, and both give the bits of
// the 16-lane walk and the rows-in-lanes network that large calls take.
#include <doctest/doctest.h>
#include <lsnif/lsnif.h>

#include "asset_rays.hpp"

#include <algorithm>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

namespace fs = std::filesystem;

TEST_CASE("hits and occlusion are the same bits whatever the number of rays per call") {
    for (const std::string name : {"armadillo_fp16.lsnif", "peterbilt_u8.lsnif"}) {
        CAPTURE(name);
        lsnif_test::OpenModel m(fs::path(LSNIF_CONFORMANCE_DIR) / name);
        std::vector<lsnif_ray> rays, leaving;
        lsnif_test::make_rays(m.model, rays, leaving);
        rays.insert(rays.end(), leaving.begin(),
                    leaving.begin() + std::min<std::size_t>(leaving.size(), 4096));
        std::vector<lsnif_hit> whole(rays.size());
        std::vector<std::uint8_t> whole_occ(rays.size());
        REQUIRE(lsnif_intersect(m.model, rays.data(), rays.size(), whole.data()) == LSNIF_OK);
        REQUIRE(lsnif_occluded(m.model, rays.data(), rays.size(), whole_occ.data()) == LSNIF_OK);
        std::size_t hits = 0;
        for (const lsnif_hit& h : whole) hits += h.hit;
        CHECK(hits > rays.size() / 10);  // real answers, not a batch of misses
        for (const std::size_t per_call : {1u, 2u, 3u, 15u, 16u, 17u}) {
            CAPTURE(per_call);
            std::vector<lsnif_hit> split(rays.size());
            std::vector<std::uint8_t> split_occ(rays.size(), 7);
            for (std::size_t i = 0; i < rays.size(); i += per_call) {
                const std::size_t n = std::min(per_call, rays.size() - i);
                REQUIRE(lsnif_intersect(m.model, rays.data() + i, n, split.data() + i) == LSNIF_OK);
                REQUIRE(lsnif_occluded(m.model, rays.data() + i, n, split_occ.data() + i) == LSNIF_OK);
            }
            CHECK(std::memcmp(split.data(), whole.data(), whole.size() * sizeof(lsnif_hit)) == 0);
            CHECK(split_occ == whole_occ);
        }
    }
}
