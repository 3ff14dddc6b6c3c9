// printf-style formatting into a std::string, for messages and report lines: one helper for
// the whole tree, with the compiler checking the arguments against the format.
#pragma once

#include <cstdarg>
#include <cstdio>
#include <string>

namespace lsnif::base {

// `format` with `args` (as std::vsnprintf), truncated to 511 characters.
inline std::string vprinted(const char* format, va_list args) {
    char buf[512];
    std::vsnprintf(buf, sizeof buf, format, args);
    return buf;
}

[[gnu::format(printf, 1, 2)]] inline std::string printed(const char* format, ...) {
    va_list args;
    va_start(args, format);
    std::string text = vprinted(format, args);
    va_end(args);
    return text;
}

}  // namespace lsnif::base
