// A value or an error message: the subset of C++23's std::expected<T, std::string> that
// lsnif::eval needs (GCC 12 in C++20 mode has no <expected>). The library never throws,
// exits or prints; every fallible call returns a Result instead.
//
//   auto r = lsnif::eval::flip(reference, test);
//   if (!r) report(r.error());   // one line naming what is wrong
//   else use(r->stats.mean);
#pragma once

#include <string>
#include <utility>
#include <variant>

namespace lsnif::eval {

// The failure side of a Result; `return Error{"..."};` converts to any Result<T>.
struct Error {
    std::string message;
};

template <class T>
class [[nodiscard]] Result {
public:
    Result(T value) : state_(std::in_place_index<0>, std::move(value)) {}
    Result(Error error) : state_(std::in_place_index<1>, std::move(error.message)) {}

    bool has_value() const noexcept { return state_.index() == 0; }
    explicit operator bool() const noexcept { return has_value(); }

    // Precondition: has_value(). Violating it throws std::bad_variant_access (a
    // programming error, as std::expected::value() reports it), never silently reads.
    T& operator*() & { return std::get<0>(state_); }
    const T& operator*() const& { return std::get<0>(state_); }
    T&& operator*() && { return std::get<0>(std::move(state_)); }
    T* operator->() { return &std::get<0>(state_); }
    const T* operator->() const { return &std::get<0>(state_); }

    // The message when !has_value(); an empty string otherwise.
    const std::string& error() const noexcept {
        static const std::string none;
        const std::string* message = std::get_if<1>(&state_);
        return message ? *message : none;
    }

private:
    std::variant<T, std::string> state_;
};

// Success without a value (e.g. a file was written).
template <>
class [[nodiscard]] Result<void> {
public:
    Result() = default;
    Result(Error error) : error_(std::move(error.message)), ok_(false) {}

    bool has_value() const noexcept { return ok_; }
    explicit operator bool() const noexcept { return ok_; }
    // The message when !has_value(); an empty string otherwise.
    const std::string& error() const noexcept { return error_; }

private:
    std::string error_;
    bool ok_ = true;
};

}  // namespace lsnif::eval
