// lsnif::image's result type: base::Result (lsnif/base/result.hpp) with a one-line message.
// The library never throws, exits or prints; every fallible call returns a Result instead.
//
//   auto r = lsnif::image::flip(reference, test);
//   if (!r) report(r.error().message);   // one line naming what is wrong
//   else use(r->stats.mean);
#pragma once

#include <lsnif/base/result.hpp>

#include <string>

namespace lsnif::image {

struct Error {
    std::string message;
};

template <class T>
using Result = base::Result<T, Error>;

}  // namespace lsnif::image
