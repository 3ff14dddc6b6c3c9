// The toolchain's one result type: a value or an error, for library calls that can fail
// (header-only, standard library only; the subset of C++23's std::expected we need, which
// GCC 12 in C++20 mode lacks). Each module picks its error type (format::Error carries a
// status code and file offset, voxelize::Error and image::Error a message) and aliases
// Result<T> = base::Result<T, Error>. Result<void, E> is success without a value (e.g. a
// file was written).
#pragma once

#include <utility>
#include <variant>

namespace lsnif::base {

template <class T, class E>
class [[nodiscard]] Result {
public:
    Result(T value) : v_(std::in_place_index<0>, std::move(value)) {}
    Result(E error) : v_(std::in_place_index<1>, std::move(error)) {}
    bool ok() const { return v_.index() == 0; }
    explicit operator bool() const { return ok(); }
    // value() and the operators require ok(); error() requires !ok().
    T& value() { return std::get<0>(v_); }
    const T& value() const { return std::get<0>(v_); }
    T& operator*() { return value(); }
    const T& operator*() const { return value(); }
    T* operator->() { return &value(); }
    const T* operator->() const { return &value(); }
    const E& error() const { return std::get<1>(v_); }

private:
    std::variant<T, E> v_;
};

template <class E>
class [[nodiscard]] Result<void, E> {
public:
    Result() = default;
    Result(E error) : error_(std::move(error)), ok_(false) {}
    bool ok() const { return ok_; }
    explicit operator bool() const { return ok(); }
    // Meaningful when !ok(); a default E otherwise.
    const E& error() const { return error_; }

private:
    E error_{};
    bool ok_ = true;
};

}  // namespace lsnif::base
