#include <lsnif/samples/sample.hpp>

namespace lsnif::samples {

const char* family_name(Family f) {
    switch (f) {
        case Family::outside: return "outside";
        case Family::surface: return "surface";
        case Family::interior: return "interior";
    }
    return "?";
}

}  // namespace lsnif::samples
