// The toolchain's one thread pool (header-only, standard library only).
//
// run_on_threads(T, fn) calls fn(t) exactly once for every t in [0, T), t = 0 on the
// calling thread and the others on persistent worker threads, and returns when all have
// finished. Workers are started on first use and kept for the life of the process, so a
// training loop that parallelizes every step does not pay a thread start per step.
//
// Determinism is the caller's: work is split by `t` (fixed shares) or handed out by an
// atomic counter whose results must not depend on which thread took which chunk
// (parallel_chunks). The pool adds no ordering of its own.
//
// Never blocks forever and never throws for lack of threads: a call made while the pool
// is busy (from inside fn, or from another thread) runs on freshly started threads, and
// if a thread cannot be started the calling thread runs the remaining shares itself. An
// exception thrown by fn is rethrown on the calling thread after every share finished.
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace lsnif::base {

// Threads to use for a request of `requested` (0 = one per hardware thread, at least 1).
inline std::uint32_t resolve_threads(std::uint32_t requested) {
    if (requested) return requested;
    return std::max(1u, std::thread::hardware_concurrency());
}

namespace detail {

// Collects the first exception any share threw.
struct FirstError {
    std::mutex m;
    std::exception_ptr e;
    void capture() {
        std::lock_guard lock(m);
        if (!e) e = std::current_exception();
    }
};

// Runs shares [first, T) on fresh threads and the caller; used when the pool is busy.
inline void run_on_fresh_threads(std::uint32_t first, std::uint32_t T,
                                 const std::function<void(std::uint32_t)>& fn, FirstError& err) {
    std::vector<std::thread> threads;
    std::uint32_t t = first + 1;
    for (; t < T; ++t) {
        try {
            threads.emplace_back([&fn, &err, t] {
                try {
                    fn(t);
                } catch (...) {
                    err.capture();
                }
            });
        } catch (...) {  // cannot start a thread: the caller runs the rest
            break;
        }
    }
    for (std::uint32_t s = first; s < T; s = (s == first ? t : s + 1)) {
        try {
            fn(s);
        } catch (...) {
            err.capture();
        }
    }
    for (std::thread& th : threads) th.join();
}

class Pool {
public:
    static Pool& instance() {
        // Never destroyed: workers blocked in wait() at process exit are simply ended,
        // and no destructor joins threads during static destruction.
        static Pool* pool = new Pool;
        return *pool;
    }

    // False when another call owns the pool; the caller then uses fresh threads.
    bool try_run(std::uint32_t T, const std::function<void(std::uint32_t)>& fn, FirstError& err) {
        // An atomic flag, not a mutex: a nested call from share 0 runs on the thread that
        // owns the pool, where try_lock on a held mutex would be undefined.
        if (busy_.exchange(true, std::memory_order_acquire)) return false;
        const std::uint32_t started = grow(T - 1);
        {
            std::lock_guard lock(m_);
            job_ = &fn;
            err_ = &err;
            shares_ = std::min(started, T - 1);
            next_share_ = 0;
            pending_ = shares_;
            ++generation_;
        }
        wake_.notify_all();
        // The caller takes share 0 and every share no worker exists for.
        for (std::uint32_t s = 0; s < T; s = (s == 0 ? shares_ + 1 : s + 1)) {
            try {
                fn(s);
            } catch (...) {
                err.capture();
            }
        }
        std::unique_lock lock(m_);
        done_.wait(lock, [&] { return pending_ == 0; });
        job_ = nullptr;
        busy_.store(false, std::memory_order_release);
        return true;
    }

private:
    Pool() = default;

    // Starts workers up to `wanted`; returns how many exist (fewer if a start failed).
    std::uint32_t grow(std::uint32_t wanted) {
        while (workers_.size() < wanted) {
            try {
                workers_.emplace_back([this] { loop(); });
            } catch (...) {
                break;
            }
        }
        return std::uint32_t(workers_.size());
    }

    void loop() {
        std::uint64_t seen = 0;
        for (;;) {
            std::unique_lock lock(m_);
            wake_.wait(lock, [&] { return generation_ != seen && next_share_ < shares_; });
            seen = generation_;
            const std::uint32_t share = 1 + next_share_++;
            const auto* fn = job_;
            FirstError* err = err_;
            lock.unlock();
            try {
                (*fn)(share);
            } catch (...) {
                err->capture();
            }
            lock.lock();
            if (--pending_ == 0) done_.notify_one();
        }
    }

    std::atomic<bool> busy_{false};  // set by the call that owns the workers
    std::mutex m_;
    std::condition_variable wake_, done_;
    std::vector<std::thread> workers_;
    const std::function<void(std::uint32_t)>* job_ = nullptr;
    FirstError* err_ = nullptr;
    std::uint64_t generation_ = 0;
    std::uint32_t shares_ = 0, next_share_ = 0, pending_ = 0;
};

}  // namespace detail

inline void run_on_threads(std::uint32_t threads, const std::function<void(std::uint32_t)>& fn) {
    const std::uint32_t T = std::max(1u, threads);
    if (T == 1) {
        fn(0);
        return;
    }
    detail::FirstError err;
    if (!detail::Pool::instance().try_run(T, fn, err)) detail::run_on_fresh_threads(0, T, fn, err);
    if (err.e) std::rethrow_exception(err.e);
}

// Calls body(t, begin, end) over [0, n) in chunks of `chunk` handed out dynamically to up
// to `threads` threads (t = the share running it). Results must not depend on which share
// ran which chunk.
template <class Body>
void parallel_chunks(std::size_t n, std::uint32_t threads, std::size_t chunk, Body&& body) {
    chunk = std::max<std::size_t>(1, chunk);
    const std::size_t chunks = (n + chunk - 1) / chunk;
    const auto T = std::uint32_t(std::clamp<std::size_t>(chunks, 1, std::max(1u, threads)));
    std::atomic<std::size_t> next{0};
    run_on_threads(T, [&](std::uint32_t t) {
        for (;;) {
            const std::size_t b = next.fetch_add(chunk, std::memory_order_relaxed);
            if (b >= n) return;
            body(t, b, std::min(n, b + chunk));
        }
    });
}

}  // namespace lsnif::base
