// lsnif::base: the shared helpers (thread pool, random numbers, affine transforms, result).
#include <lsnif/base/affine.hpp>
#include <lsnif/base/huge_pages.hpp>
#include <lsnif/base/math.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/base/result.hpp>

#include <doctest/doctest.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

using namespace lsnif::base;

TEST_CASE("run_on_threads calls every share exactly once, on distinct threads") {
    for (std::uint32_t T : {1u, 2u, 3u, 8u}) {
        std::vector<std::atomic<int>> calls(T);
        std::vector<std::thread::id> ids(T);
        run_on_threads(T, [&](std::uint32_t t) {
            calls[t].fetch_add(1);
            ids[t] = std::this_thread::get_id();
        });
        for (std::uint32_t t = 0; t < T; ++t) CHECK(calls[t].load() == 1);
        CHECK(ids[0] == std::this_thread::get_id());  // share 0 is the caller
        for (std::uint32_t t = 1; t < T; ++t) CHECK(ids[t] != ids[0]);
    }
}

TEST_CASE("the pool's workers persist between calls") {
    // A thread-local count survives only on a thread that served an earlier call: with a
    // fresh thread per call every worker would report 1.
    static thread_local int served = 0;
    std::atomic<int> most{0};
    for (int call = 0; call < 64; ++call)
        run_on_threads(2, [&](std::uint32_t t) {
            if (t == 0) return;
            const int n = ++served;
            for (int m = most.load(); n > m && !most.compare_exchange_weak(m, n);) {
            }
        });
    CHECK(most.load() > 1);
}

TEST_CASE("nested and concurrent calls complete instead of deadlocking") {
    std::atomic<int> inner{0};
    run_on_threads(3, [&](std::uint32_t) { run_on_threads(3, [&](std::uint32_t) { inner.fetch_add(1); }); });
    CHECK(inner.load() == 9);
    std::atomic<int> total{0};
    std::thread other([&] { run_on_threads(4, [&](std::uint32_t) { total.fetch_add(1); }); });
    run_on_threads(4, [&](std::uint32_t) { total.fetch_add(1); });
    other.join();
    CHECK(total.load() == 8);
}

TEST_CASE("an exception in a share reaches the caller after every share finished") {
    std::atomic<int> finished{0};
    CHECK_THROWS_AS(run_on_threads(4,
                                   [&](std::uint32_t t) {
                                       finished.fetch_add(1);
                                       if (t == 2) throw std::runtime_error("share 2");
                                   }),
                    std::runtime_error);
    CHECK(finished.load() == 4);
    std::atomic<int> after{0};  // the pool is usable again
    run_on_threads(2, [&](std::uint32_t) { after.fetch_add(1); });
    CHECK(after.load() == 2);
}

TEST_CASE("parallel_chunks covers [0, n) exactly once") {
    for (std::size_t n : {std::size_t(0), std::size_t(1), std::size_t(1000), std::size_t(4097)}) {
        std::vector<std::atomic<int>> seen(n);
        parallel_chunks(n, 3, 64, [&](std::uint32_t, std::size_t b, std::size_t e) {
            for (std::size_t i = b; i < e; ++i) seen[i].fetch_add(1);
        });
        for (std::size_t i = 0; i < n; ++i) REQUIRE(seen[i].load() == 1);
    }
    CHECK(resolve_threads(5) == 5);
    CHECK(resolve_threads(0) >= 1);
}

TEST_CASE("SplitMix64 reproduces the reference sequence") {
    // splitmix64 seeded with 0: the first outputs of the reference implementation.
    SplitMix64 r{0};
    CHECK(r.next() == 0xE220A8397B1DCDAFull);
    CHECK(r.next() == 0x6E789E6AA1B965F4ull);
    CHECK(r.next() == 0x06C45D188009454Full);
    SplitMix64 u{42};
    for (int i = 0; i < 1000; ++i) {
        const float f = u.uniform01f();
        const double d = u.u01();
        const float g = u.uniform(-2.0f, 3.0f);
        REQUIRE((f >= 0.0f && f < 1.0f));
        REQUIRE((d >= 0.0 && d < 1.0));
        REQUIRE((g >= -2.0f && g < 3.0f));
    }
}

TEST_CASE("invert_linear inverts, keeps the sign of mirrors and applies one singularity rule") {
    // Rotation by 30 degrees about y, scaled by 2, mirrored in x, translated.
    const float c = std::cos(0.5235988f), s = std::sin(0.5235988f);
    const float m[12] = {-2 * c, 0, 2 * s, 1, 0, 2, 0, -3, 2 * s, 0, 2 * c, 5};
    const auto li = invert_linear(m);
    REQUIRE(li.has_value());
    CHECK(li->det < 0);
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) {
            double v = 0;
            for (int j = 0; j < 3; ++j) v += li->inv[r][j] * m[4 * j + k];
            CHECK(v == doctest::Approx(r == k ? 1.0 : 0.0).epsilon(1e-6));
        }
    // A normal of the plane x = 0 in object space maps to the normal of its image.
    const auto n = normal_matrix(*li);
    const float nx[3] = {n[0], n[3], n[6]};       // N (1, 0, 0)
    const float tangent[3] = {m[1], m[5], m[9]};  // image of (0, 1, 0), which lies in the plane
    CHECK(nx[0] * tangent[0] + nx[1] * tangent[1] + nx[2] * tangent[2] == doctest::Approx(0.0).epsilon(1e-6));
    // Tiny but regular scales are fine; a flattened axis, NaN or infinity are not.
    const float tiny[12] = {1e-5f, 0, 0, 0, 0, 1e-5f, 0, 0, 0, 0, 1e-5f, 0};
    CHECK(invert_linear(tiny).has_value());
    const float flat[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1e-13f, 0};
    CHECK_FALSE(invert_linear(flat).has_value());
    float bad[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
    bad[3] = NAN;
    CHECK_FALSE(invert_linear(bad).has_value());
    bad[3] = INFINITY;
    CHECK_FALSE(invert_linear(bad).has_value());
}

TEST_CASE("Result holds a value or an error") {
    struct Err {
        std::string message;
    };
    Result<int, Err> good = 7, bad = Err{"no"};
    CHECK(good.ok());
    CHECK(*good == 7);
    CHECK_FALSE(bad);
    CHECK(bad.error().message == "no");
}

TEST_CASE("allocate_large: large blocks on 2 MiB boundaries, small ones from operator new, all usable") {
    for (const std::size_t n :
         {std::size_t(1), std::size_t(4096), lsnif::base::kHugePageBytes - 1, lsnif::base::kHugePageBytes,
          lsnif::base::kHugePageBytes + 1, std::size_t(5) * lsnif::base::kHugePageBytes + 123}) {
        auto* p = static_cast<unsigned char*>(lsnif::base::allocate_large(n));
        REQUIRE(p != nullptr);
        if (n >= lsnif::base::kHugePageBytes)
            CHECK(reinterpret_cast<std::uintptr_t>(p) % lsnif::base::kHugePageBytes == 0);
        std::memset(p, 0xA5, n);  // every byte writable (ASan checks the bounds)
        CHECK(p[n - 1] == 0xA5);
        lsnif::base::free_large(p, n);
    }
}

// base/math.hpp: lsnif's own elementary functions, which give the same bits on every machine
// because they use +, -, *, / and sqrt alone. Here: that they are accurate (against the C
// library, which is accurate but may round differently elsewhere) and right at the edges.
TEST_CASE("base::exp, log, log1p, pow, acos agree with the C library to a few units in the last place") {
    const auto ulps = [](double got, double want) {
        if (got == want) return 0.0;
        return std::fabs(got - want) / std::fabs(std::nextafter(want, INFINITY) - want);
    };
    double worst_exp = 0, worst_log = 0, worst_log1p = 0, worst_pow = 0, worst_acos = 0;
    lsnif::base::SplitMix64 rng{12345};
    for (int i = 0; i < 200000; ++i) {
        const double u = double(rng.next() >> 11) * 0x1p-53;  // [0, 1)
        const double x = -700.0 + 1400.0 * u;
        worst_exp = std::max(worst_exp, ulps(lsnif::base::exp(x), std::exp(x)));
        const double y = std::ldexp(0.5 + u, int(rng.next() % 400) - 200);
        worst_log = std::max(worst_log, ulps(lsnif::base::log(y), std::log(y)));
        const double z = (u - 0.5) * std::ldexp(1.0, -int(rng.next() % 40));
        worst_log1p = std::max(worst_log1p, ulps(lsnif::base::log1p(z), std::log1p(z)));
        const double a = 0.01 + u, b = double(rng.next() % 1000) / 1000.0;
        worst_pow = std::max(worst_pow, ulps(lsnif::base::pow(a, b), std::pow(a, b)));
        const double c = 2.0 * u - 1.0;
        worst_acos = std::max(worst_acos, ulps(lsnif::base::acos(c), std::acos(c)));
    }
    MESSAGE("largest differences in ulps: exp " << worst_exp << ", log " << worst_log << ", log1p "
                                                << worst_log1p << ", pow " << worst_pow << ", acos "
                                                << worst_acos);
    CHECK(worst_exp <= 4);
    CHECK(worst_log <= 4);
    CHECK(worst_log1p <= 4);
    CHECK(worst_pow <= 16);  // exp(b log a): log a's rounding, scaled by b
    CHECK(worst_acos <= 8);  // the series of asin, summed term by term
    // sin and cos over the angles views are drawn from (a few turns either way): within a
    // few ulps where the value is not near zero, and absolutely within 2^-52 near zero.
    double worst_sin = 0, worst_cos = 0;
    for (int i = 0; i < 200000; ++i) {
        const double x = (double(rng.next() >> 11) * 0x1p-53 - 0.5) * 40.0;
        const auto err = [&](double got, double want) {
            return std::fabs(want) > 1e-3 ? ulps(got, want) : std::fabs(got - want) / 0x1p-52;
        };
        worst_sin = std::max(worst_sin, err(lsnif::base::sin(x), std::sin(x)));
        worst_cos = std::max(worst_cos, err(lsnif::base::cos(x), std::cos(x)));
    }
    MESSAGE("sin " << worst_sin << ", cos " << worst_cos << " ulps at most");
    CHECK(worst_sin <= 4);
    CHECK(worst_cos <= 4);
    CHECK(lsnif::base::sin(0.0) == 0.0);
    CHECK(lsnif::base::cos(0.0) == 1.0);
    CHECK(std::isnan(lsnif::base::sin(INFINITY)));
    // Exact and edge values.
    CHECK(lsnif::base::exp(0.0) == 1.0);
    CHECK(lsnif::base::exp(800.0) == INFINITY);
    CHECK(lsnif::base::exp(-800.0) == 0.0);
    CHECK(std::isnan(lsnif::base::exp(NAN)));
    CHECK(lsnif::base::exp(-740.0) > 0.0);  // subnormal, rounded by ldexp
    CHECK(ulps(lsnif::base::exp(-740.0), std::exp(-740.0)) <= 1);
    CHECK(lsnif::base::log(1.0) == 0.0);
    CHECK(lsnif::base::log(0.0) == -INFINITY);
    CHECK(std::isnan(lsnif::base::log(-1.0)));
    CHECK(lsnif::base::log(INFINITY) == INFINITY);
    CHECK(ulps(lsnif::base::log(0x1p-1070), std::log(0x1p-1070)) <= 4);  // subnormal argument
    CHECK(lsnif::base::log1p(0.0) == 0.0);
    CHECK(std::isnan(lsnif::base::log1p(-2.0)));
    CHECK(lsnif::base::pow(0.1, 0.0) == 1.0);
    CHECK(lsnif::base::pow(0.0, 0.5) == 0.0);
    CHECK(lsnif::base::acos(1.0) == 0.0);
    CHECK(ulps(lsnif::base::acos(-1.0), std::acos(-1.0)) <= 1);
    CHECK(ulps(lsnif::base::acos(0.0), std::acos(0.0)) <= 1);
    CHECK(std::isnan(lsnif::base::acos(1.5)));
    // pow_int is repeated squaring: exact for small integer powers; each squaring doubles
    // the relative error, so Adam's 0.99^4800 is good to ~1e-12 (its bias correction needs
    // far less).
    CHECK(lsnif::base::pow_int(3.0, 5) == 243.0);
    CHECK(lsnif::base::pow_int(0.9, 0) == 1.0);
    for (const std::uint64_t t : {1u, 7u, 100u, 1200u, 4800u}) {
        const double want = std::pow(0.99, double(t));
        CHECK(std::fabs(lsnif::base::pow_int(0.99, t) - want) <= 1e-12 * want);
    }
}
