// lsnif::cache: SHA-256 through nettle, and the entry files of docs/pipeline.md "The cache".
#include <lsnif/cache/cache.hpp>
#include <lsnif/format/container.hpp>

#include <nettle/sha2.h>

#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <system_error>

namespace lsnif::cache {

namespace fs = std::filesystem;

struct Sha256::State {
    sha256_ctx ctx;
};

Sha256::Sha256() : state_(std::make_unique<State>()) {
    sha256_init(&state_->ctx);
}
Sha256::~Sha256() = default;
Sha256::Sha256(Sha256&&) noexcept = default;
Sha256& Sha256::operator=(Sha256&&) noexcept = default;

Sha256& Sha256::update(std::span<const std::uint8_t> bytes) {
    sha256_update(&state_->ctx, bytes.size(), bytes.data());
    return *this;
}

Sha256& Sha256::update(std::string_view text) {
    return update({reinterpret_cast<const std::uint8_t*>(text.data()), text.size()});
}

std::array<std::uint8_t, 32> Sha256::digest() {
    std::array<std::uint8_t, 32> d{};
    sha256_digest(&state_->ctx, d.size(), d.data());
    return d;
}

namespace {

std::string to_hex(std::span<const std::uint8_t> bytes) {
    static const char digits[] = "0123456789abcdef";
    std::string s;
    for (std::uint8_t b : bytes) {
        s += digits[b >> 4];
        s += digits[b & 15];
    }
    return s;
}

constexpr char kMagic[8] = {'L', 'S', 'N', 'I', 'F', 'C', 'E', '1'};
constexpr std::string_view kChecksumDomain = "lsnif-cache-entry/1\n";

void put_u64(std::uint8_t* p, std::uint64_t v) {
    for (int i = 0; i < 8; ++i) p[i] = std::uint8_t(v >> (8 * i));
}
std::uint64_t get_u64(const std::uint8_t* p) {
    std::uint64_t v = 0;
    for (int i = 0; i < 8; ++i) v |= std::uint64_t(p[i]) << (8 * i);
    return v;
}

// The checksum of an entry: domain, key, the two sizes as stored, record, payload.
std::array<std::uint8_t, 32> entry_checksum(std::string_view key, const std::uint8_t* sizes,
                                            std::span<const std::uint8_t> record,
                                            std::span<const std::uint8_t> payload) {
    Sha256 h;
    h.update(kChecksumDomain).update(key).update({sizes, 16}).update(record).update(payload);
    return h.digest();
}

// The whole file, or an error message; refuses files larger than kMaxEntrySize.
Result<std::vector<std::uint8_t>> read_all(const fs::path& path) {
    std::error_code ec;
    const auto size = fs::file_size(path, ec);
    if (ec) return Error{path.string() + ": " + ec.message()};
    if (size > kMaxEntrySize)
        return Error{path.string() + ": larger than " + std::to_string(kMaxEntrySize) + " bytes"};
    std::ifstream f(path, std::ios::binary);
    if (!f) return Error{path.string() + ": cannot open"};
    std::vector<std::uint8_t> bytes{std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
    if (f.bad()) return Error{path.string() + ": read error"};
    return bytes;
}

// Why `bytes` is not a valid entry for `key`; empty when it is.
std::string entry_problem(std::span<const std::uint8_t> bytes, std::string_view key) {
    if (bytes.size() < kEntryHeaderSize)
        return "truncated: " + std::to_string(bytes.size()) + " bytes, shorter than the header";
    if (std::memcmp(bytes.data(), kMagic, sizeof kMagic) != 0) return "not a cache entry (bad magic)";
    if (std::string_view(reinterpret_cast<const char*>(bytes.data() + 56), 64) != key)
        return "stored under the wrong key";
    const std::uint64_t r = get_u64(bytes.data() + 8), p = get_u64(bytes.data() + 16);
    if (r > kMaxEntrySize || p > kMaxEntrySize || kEntryHeaderSize + r + p != bytes.size())
        return "sizes (record " + std::to_string(r) + ", payload " + std::to_string(p) +
               ") do not match the file's " + std::to_string(bytes.size()) + " bytes (truncated or torn)";
    const auto sum = entry_checksum(key, bytes.data() + 8, bytes.subspan(kEntryHeaderSize, r),
                                    bytes.subspan(kEntryHeaderSize + r, p));
    if (std::memcmp(sum.data(), bytes.data() + 24, sum.size()) != 0)
        return "checksum mismatch (altered or torn)";
    return {};
}

}  // namespace

std::string Sha256::hex() {
    const auto d = digest();
    return to_hex(d);
}

std::string sha256_hex(std::span<const std::uint8_t> bytes) {
    return Sha256().update(bytes).hex();
}

// Built by appending: GCC 12 warns falsely (-Wrestrict) on "'" + std::string(view) + "...".
std::string not_a_key(std::string_view key) {
    std::string s = "'";
    s.append(key);
    s.append("' is not a cache key (64 lowercase hexadecimal digits)");
    return s;
}

bool valid_key(std::string_view key) {
    if (key.size() != 64) return false;
    for (char c : key)
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
    return true;
}

Result<Store> Store::open(const fs::path& dir) {
    const fs::path root = dir / "v1";
    std::error_code ec;
    fs::create_directories(root / "entries", ec);
    if (ec) return Error{dir.string() + ": cannot create the cache directory: " + ec.message()};
    return Store(root);
}

fs::path Store::entry_path(std::string_view key) const {
    return root_ / "entries" / std::string(key.substr(0, 2)) / (std::string(key) + ".entry");
}

std::vector<std::uint8_t> encode_entry(std::string_view key, const Entry& entry) {
    std::vector<std::uint8_t> bytes(kEntryHeaderSize);
    std::memcpy(bytes.data(), kMagic, sizeof kMagic);
    put_u64(bytes.data() + 8, entry.record.size());
    put_u64(bytes.data() + 16, entry.payload.size());
    std::memcpy(bytes.data() + 56, key.data(), 64);
    const std::span<const std::uint8_t> record(reinterpret_cast<const std::uint8_t*>(entry.record.data()),
                                               entry.record.size());
    const auto sum = entry_checksum(key, bytes.data() + 8, record, entry.payload);
    std::memcpy(bytes.data() + 24, sum.data(), sum.size());
    bytes.insert(bytes.end(), record.begin(), record.end());
    bytes.insert(bytes.end(), entry.payload.begin(), entry.payload.end());
    return bytes;
}

Result<Entry> decode_entry(std::span<const std::uint8_t> bytes, std::string_view key) {
    if (std::string problem = entry_problem(bytes, key); !problem.empty()) return Error{problem};
    const std::uint64_t r = get_u64(bytes.data() + 8);
    Entry entry;
    entry.record.assign(reinterpret_cast<const char*>(bytes.data()) + kEntryHeaderSize, r);
    entry.payload.assign(bytes.begin() + std::ptrdiff_t(kEntryHeaderSize + r), bytes.end());
    return entry;
}

Lookup Store::get(std::string_view key) const {
    Lookup out;
    if (!valid_key(key)) {
        out.status = Status::corrupt;
        out.problem = not_a_key(key);
        return out;
    }
    const fs::path path = entry_path(key);
    std::error_code ec;
    if (!fs::exists(path, ec)) return out;  // miss
    auto bytes = read_all(path);
    auto entry = bytes ? decode_entry(*bytes, key) : Result<Entry>(bytes.error());
    if (!entry) {
        out.status = Status::corrupt;
        out.problem = bytes ? path.string() + ": " + entry.error().message : entry.error().message;
        fs::remove(path, ec);  // a concurrent put() may have replaced it: that only costs a rebuild
        return out;
    }
    out.status = Status::hit;
    out.entry = std::move(*entry);
    return out;
}

Result<void> Store::put(std::string_view key, const Entry& entry) const {
    if (!valid_key(key)) return Error{not_a_key(key)};
    if (entry.record.size() > kMaxEntrySize || entry.payload.size() > kMaxEntrySize)
        return Error{"cache entry " + std::string(key) + " is larger than " + std::to_string(kMaxEntrySize) +
                     " bytes"};
    const std::vector<std::uint8_t> bytes = encode_entry(key, entry);

    const fs::path path = entry_path(key);
    std::error_code ec;
    fs::create_directories(path.parent_path(), ec);
    if (ec) return Error{path.parent_path().string() + ": cannot create: " + ec.message()};
    // A temporary file next to the entry, fsync'ed, then renamed over it (format's helper).
    if (const format::Error e = format::write_bytes_atomically(path.string(), bytes)) return Error{e.message};
    return {};
}

}  // namespace lsnif::cache
