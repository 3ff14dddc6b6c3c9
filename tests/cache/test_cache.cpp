#include <doctest/doctest.h>

#include <lsnif/cache/cache.hpp>
#include <lsnif/cache/remote.hpp>
#include "../test_data.hpp"

#include <sys/wait.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

using namespace lsnif::cache;
namespace fs = std::filesystem;

namespace {

fs::path fresh_dir(const std::string& name) {
    return lsnif::test::fresh_dir(LSNIF_CACHE_WORK_DIR, name, false);  // Store::open creates it
}

std::string key_of(const std::string& text) {
    return Sha256().update(text).hex();
}

Entry entry_of(const std::string& record, std::size_t payload_bytes, std::uint8_t fill) {
    return {record, std::vector<std::uint8_t>(payload_bytes, fill)};
}

Store open_store(const fs::path& dir) {
    auto s = Store::open(dir);
    REQUIRE_MESSAGE(s.ok(), (s.ok() ? "" : s.error().message));
    return *s;
}

std::vector<char> file_bytes(const fs::path& p) {
    std::ifstream f(p, std::ios::binary);
    return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

RemoteOptions server(const std::string& url, double timeout_seconds = 10) {
    RemoteOptions o;
    o.url = url;
    o.timeout_seconds = timeout_seconds;
    return o;
}

CacheOptions cache_at(const std::string& location, const std::string& local = {},
                      double timeout_seconds = 10) {
    CacheOptions o;
    o.location = location;
    o.local = local;
    o.timeout_seconds = timeout_seconds;
    return o;
}

void write_bytes(const fs::path& p, const std::vector<char>& bytes) {
    std::ofstream f(p, std::ios::binary | std::ios::trunc);
    f.write(bytes.data(), std::streamsize(bytes.size()));
}

}  // namespace

TEST_CASE("SHA-256 gives FIPS 180-4's example digests") {
    CHECK(Sha256().hex() == "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    CHECK(key_of("abc") == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    CHECK(key_of("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq") ==
          "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
    // A million 'a', fed in uneven pieces: incremental updates hash the concatenation.
    Sha256 h;
    const std::string piece(999, 'a');
    std::size_t fed = 0;
    while (fed + piece.size() <= 1000000) h.update(piece), fed += piece.size();
    h.update(std::string(1000000 - fed, 'a'));
    CHECK(h.hex() == "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
}

TEST_CASE("an entry round trips; an absent key is a miss; keys are checked") {
    const Store store = open_store(fresh_dir("roundtrip"));
    const std::string k = key_of("dragon");
    CHECK(store.get(k).status == Status::miss);
    const Entry e = entry_of(R"({"class":"complex"})", 5000, 0xab);
    REQUIRE(store.put(k, e).ok());
    const Lookup l = store.get(k);
    REQUIRE(l.status == Status::hit);
    CHECK(l.entry == e);
    // An empty payload (an object that stays BVH) is an entry too.
    const std::string k2 = key_of("hairball");
    REQUIRE(store.put(k2, entry_of(R"({"class":"simple"})", 0, 0)).ok());
    CHECK(store.get(k2).status == Status::hit);
    CHECK(store.get(k2).entry.payload.empty());
    // Replacing an entry.
    REQUIRE(store.put(k, entry_of("{}", 10, 1)).ok());
    CHECK(store.get(k).entry == entry_of("{}", 10, 1));
    // No temporary file is left next to the entries.
    for (const auto& f : fs::recursive_directory_iterator(store.root()))
        if (f.is_regular_file()) CHECK_MESSAGE(f.path().extension() == ".entry", f.path());
    CHECK_FALSE(valid_key("ABC"));
    CHECK_FALSE(store.put("../../etc/passwd", e).ok());
    CHECK(store.get(std::string(64, 'G')).status == Status::corrupt);
}

TEST_CASE("truncated, torn, altered and misplaced entries are detected, removed and rebuilt") {
    const Store store = open_store(fresh_dir("damage"));
    const std::string k = key_of("armadillo");
    const Entry e = entry_of(R"({"class":"complex","reasons":["52000 triangles"]})", 20000, 0x5a);
    REQUIRE(store.put(k, e).ok());
    const fs::path path = store.entry_path(k);
    const std::vector<char> good = file_bytes(path);

    struct Damage {
        const char* name;
        std::vector<char> bytes;
        const char* problem;
    };
    std::vector<Damage> damages;
    damages.push_back({"empty file", {}, "truncated"});
    damages.push_back({"header only", {good.begin(), good.begin() + 120}, "do not match"});
    damages.push_back({"payload cut short", {good.begin(), good.end() - 1}, "do not match"});
    std::vector<char> longer = good;
    longer.push_back(0);
    damages.push_back({"trailing byte", longer, "do not match"});
    std::vector<char> flipped = good;
    flipped[good.size() - 100] ^= 1;
    damages.push_back({"one payload bit", flipped, "checksum"});
    std::vector<char> record = good;
    record[130] ^= 0x20;
    damages.push_back({"one record bit", record, "checksum"});
    std::vector<char> magic = good;
    magic[0] = 'X';
    damages.push_back({"magic", magic, "bad magic"});
    // Half of one write and half of another (a torn copy): sizes add up, the checksum does not.
    const std::string k_other = key_of("armadillo-2");
    REQUIRE(store.put(k_other, entry_of(R"({"class":"complex","reasons":["52000 triangles"]})", 20000, 0x5b))
                .ok());
    std::vector<char> torn = good;
    const std::vector<char> other = file_bytes(store.entry_path(k_other));
    std::copy(other.begin() + std::ptrdiff_t(good.size() / 2), other.end(),
              torn.begin() + std::ptrdiff_t(good.size() / 2));
    damages.push_back({"torn", torn, "checksum"});
    // An intact entry copied under another key's name.
    damages.push_back({"misplaced", other, "wrong key"});

    for (const Damage& d : damages) {
        INFO(d.name);
        write_bytes(path, d.bytes);
        const Lookup l = store.get(k);
        CHECK(l.status == Status::corrupt);
        CHECK_MESSAGE(l.problem.find(path.string()) == 0, l.problem);
        CHECK_MESSAGE(l.problem.find(d.problem) != std::string::npos, l.problem);
        CHECK_FALSE(fs::exists(path));  // removed: never used again
        CHECK(store.get(k).status == Status::miss);
        REQUIRE(store.put(k, e).ok());  // rebuilt
        CHECK(store.get(k).entry == e);
    }
}

TEST_CASE("processes writing and reading one key at the same time never see a mixed entry") {
    const Store store = open_store(fresh_dir("concurrent"));
    const std::string k = key_of("shared");
    // Writers store different contents under one key (the worst case: a conversion's
    // results are identical for one key); a reader must always see one whole entry.
    constexpr int kWriters = 4, kRounds = 60;
    std::vector<pid_t> children;
    for (int w = 0; w < kWriters; ++w) {
        const pid_t pid = fork();
        REQUIRE(pid >= 0);
        if (pid == 0) {
            int bad = 0;
            for (int r = 0; r < kRounds; ++r) {
                const Entry e = entry_of("{\"writer\":" + std::to_string(w) + "}", 200000 + std::size_t(w),
                                         std::uint8_t(w));
                if (!store.put(k, e).ok()) ++bad;
                const Lookup l = store.get(k);
                if (l.status == Status::corrupt) ++bad;
                if (l.status == Status::hit) {
                    const int who = l.entry.record[10] - '0';
                    if (who < 0 || who >= kWriters ||
                        l.entry != entry_of(l.entry.record, 200000 + std::size_t(who), std::uint8_t(who)))
                        ++bad;
                }
            }
            _exit(bad == 0 ? 0 : 1);
        }
        children.push_back(pid);
    }
    for (pid_t pid : children) {
        int status = 0;
        REQUIRE(waitpid(pid, &status, 0) == pid);
        CHECK(WIFEXITED(status));
        CHECK_MESSAGE(WEXITSTATUS(status) == 0, "a writer saw a failed put, a corrupt or a mixed entry");
    }
    const Lookup last = store.get(k);
    CHECK(last.status == Status::hit);
    for (const auto& f : fs::recursive_directory_iterator(store.root()))
        if (f.is_regular_file()) CHECK_MESSAGE(f.path().extension() == ".entry", f.path());
}

TEST_CASE("a cache directory that cannot be created is an error naming it") {
    const fs::path dir = fresh_dir("blocked");
    fs::create_directories(dir.parent_path());
    std::ofstream(dir) << "a file, not a directory";
    auto s = Store::open(dir);
    REQUIRE_FALSE(s.ok());
    CHECK(s.error().message.find(dir.string()) == 0);
}

TEST_CASE("encode_entry and decode_entry: the bytes every level stores, verified on the way back") {
    const std::string key = std::string(64, 'a');
    const Entry e{"{\"class\":\"simple\"}", {1, 2, 3, 4}};
    const std::vector<std::uint8_t> bytes = encode_entry(key, e);
    CHECK(bytes.size() == kEntryHeaderSize + e.record.size() + e.payload.size());
    auto back = decode_entry(bytes, key);
    REQUIRE(back.ok());
    CHECK(*back == e);
    CHECK(decode_entry(bytes, std::string(64, 'b')).error().message == "stored under the wrong key");
    std::vector<std::uint8_t> torn = bytes;
    torn.resize(torn.size() - 1);
    CHECK(decode_entry(torn, key).error().message.find("do not match the file's") != std::string::npos);
    const std::string html = "<html>502 Bad Gateway</html>";  // what a proxy may answer instead
    CHECK_FALSE(decode_entry({reinterpret_cast<const std::uint8_t*>(html.data()), html.size()}, key).ok());
}

TEST_CASE("a --cache value is a directory or an http(s) URL, never a URL taken for a directory") {
    CHECK(is_url("http://host/x"));
    CHECK(is_url("https://host:8443/"));
    CHECK(is_url("s3://bucket/x"));
    CHECK(is_url("git+ssh://h/x"));
    CHECK_FALSE(is_url("cache"));
    CHECK_FALSE(is_url("/abs/dir"));
    CHECK_FALSE(is_url("./http:/x"));
    CHECK_FALSE(is_url("://x"));
    CHECK_FALSE(is_url("1ab://x"));
    for (const char* url :
         {"http://127.0.0.1:8080/cache", "https://cache.example.org/lsnif/", "http://[::1]:80/c"})
        CHECK_MESSAGE(Remote::open(server(url)).ok(), url);
    const std::pair<const char*, const char*> refused[] = {
        {"ftp://host/x", "not an http:// or https:// URL"},
        {"s3://bucket/x", "not an http:// or https:// URL"},
        {"http://", "no host"},
        {"http://:80/x", "no host"},
        {"http://u:p@host/x", "credentials in the URL"},
        {"http://host/x?a=1", "a query or fragment"},
        {"http://host:0/x", "port '0' is not 1..65535"},
        {"http://host:99999/x", "port '99999' is not 1..65535"},
        {"http://host:8a/x", "port '8a' is not 1..65535"},
        {"http://host/a b", "white space"}};
    for (const auto& [url, why] : refused) {
        auto r = Remote::open(server(url));
        REQUIRE_MESSAGE(!r.ok(), url);
        CHECK_MESSAGE(r.error().message.find(why) != std::string::npos, r.error().message);
        CHECK(r.error().message.rfind(std::string("--cache ") + url, 0) == 0);
    }
    CHECK_FALSE(Remote::open(server("http://host/x", 0)).ok());  // a timeout of 0
    const std::filesystem::path cwd = std::filesystem::current_path();
    std::filesystem::current_path(lsnif::test::fresh_dir(LSNIF_CACHE_WORK_DIR, "url_not_dir", true));
    CHECK_FALSE(Cache::open(cache_at("s3://bucket/x")).ok());
    CHECK_FALSE(std::filesystem::exists("s3:"));
    CHECK_FALSE(Cache::open(cache_at("dir", "local")).ok());  // a local level goes in front of a server only
    std::filesystem::current_path(cwd);
}

TEST_CASE("a cache server that cannot be reached is unavailable, once, and puts are not lost locally") {
    // Port 9 (discard) on the loopback: nothing listens in a test sandbox, the connection is refused.
    auto cache = Cache::open(cache_at("http://127.0.0.1:9/c", fresh_dir("unreachable_local").string(), 2));
    REQUIRE(cache.ok());
    const std::string key(64, 'c');
    const Lookup miss = cache->get(key);
    CHECK(miss.status == Status::unavailable);
    auto stored = cache->put(key, Entry{"r", {}});
    REQUIRE(stored.ok());
    CHECK(*stored);  // the local level took it
    const std::vector<std::string> warnings = cache->take_warnings();
    REQUIRE(warnings.size() == 1);  // one for the get and the put
    CHECK(warnings[0].find("cache server is unavailable") != std::string::npos);
    CHECK(cache->get(key).status == Status::hit);  // from the local level, the server not asked
    CHECK(cache->take_warnings().empty());
    CHECK(cache->describe().find("http://127.0.0.1:9/c") == 0);
}
