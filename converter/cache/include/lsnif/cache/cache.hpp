// lsnif::cache — a content-addressed store of conversion results, shared between runs,
// processes and machines (docs/pipeline.md "The cache"): a directory (Store), an HTTP(S)
// server (Remote, lsnif/cache/remote.hpp) or both, a directory in front of a server (Cache).
//
// A result is stored under a key that the caller derives from everything that determines it
// (the converter hashes the geometry, the settings and the tool's build identity with
// Sha256). One entry is one file, DIR/v1/entries/KK/KEY.entry, written to a temporary file
// in the same directory and renamed into place: a reader sees a whole entry or none, and two
// writers of one key never leave a mixed one (the last rename wins). Every entry carries its
// own SHA-256, so a torn, truncated or altered entry (a crash, a disk, an interrupted copy
// between machines) is detected on reading, reported, removed, and never used.
//
// Contract: nothing here throws, exits or prints; failures come back as a one-line message
// naming the file. Store is a value (a directory path): copy it freely, use it from any
// thread or process.
#pragma once

#include <lsnif/base/result.hpp>

#include <array>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace lsnif::cache {

struct Error {
    std::string message;
};
template <class T>
using Result = base::Result<T, Error>;

// SHA-256 (FIPS 180-4), computed by Debian's nettle. Feed bytes with update(), then read the
// digest once with digest() or hex(); the object may not be updated after that.
class Sha256 {
public:
    Sha256();
    ~Sha256();
    Sha256(Sha256&&) noexcept;
    Sha256& operator=(Sha256&&) noexcept;
    Sha256& update(std::span<const std::uint8_t> bytes);
    Sha256& update(std::string_view text);
    std::array<std::uint8_t, 32> digest();
    std::string hex();  // 64 lowercase hexadecimal digits

private:
    struct State;
    std::unique_ptr<State> state_;
};

// The digest of `bytes` as 64 lowercase hexadecimal digits.
std::string sha256_hex(std::span<const std::uint8_t> bytes);

// What a key must look like: 64 lowercase hexadecimal digits (a SHA-256).
bool valid_key(std::string_view key);
// Why `key` is not valid_key ("'K' is not a cache key (...)"), the message every level gives.
std::string not_a_key(std::string_view key);

// One stored result: a record (UTF-8 text; the converter stores JSON) and an optional
// payload (the converter stores the .lsnif bytes; empty when the object stays BVH).
struct Entry {
    std::string record;
    std::vector<std::uint8_t> payload;
    bool operator==(const Entry&) const = default;
};

// The bytes of `entry` stored under `key` (valid_key, sizes at most kMaxEntrySize): the
// entry file layout below. Every level stores exactly these bytes.
std::vector<std::uint8_t> encode_entry(std::string_view key, const Entry& entry);
// The entry in `bytes` if they are a whole, intact entry stored under `key`; otherwise what
// is wrong with them (truncated, torn, altered, another key, not an entry at all).
Result<Entry> decode_entry(std::span<const std::uint8_t> bytes, std::string_view key);

enum class Status {
    hit,
    miss,
    corrupt,      // the stored bytes are not an intact entry for the key: never used
    unavailable,  // the server could not be asked (down, slow, refusing): a miss, with a warning
};

struct Lookup {
    Status status = Status::miss;
    Entry entry;          // when hit
    std::string problem;  // when corrupt or unavailable: "FILE or URL: what is wrong"
};

class Store {
public:
    // Opens the store in `dir`, creating DIR/v1/entries as needed. Fails when the directory
    // cannot be created or is not writable.
    static Result<Store> open(const std::filesystem::path& dir);

    // The entry stored under `key` (valid_key), a miss, or a corrupt entry: wrong magic,
    // version or key, sizes that do not add up to the file's, or a checksum mismatch. A corrupt
    // entry is removed so that the next put() replaces it.
    Lookup get(std::string_view key) const;

    // Stores `entry` under `key` (valid_key), replacing what was there, atomically.
    Result<void> put(std::string_view key, const Entry& entry) const;

    std::filesystem::path entry_path(std::string_view key) const;
    const std::filesystem::path& root() const { return root_; }

private:
    explicit Store(std::filesystem::path root) : root_(std::move(root)) {}
    std::filesystem::path root_;  // DIR/v1
};

// Entry file layout (all integers little-endian), version 1:
//   0   8   magic "LSNIFCE1"
//   8   8   record size R
//   16  8   payload size P
//   24  32  SHA-256 of ("lsnif-cache-entry/1\n", the 64-digit key, bytes 8..23, record, payload)
//   56  64  the key, ASCII
//   120 R   record
//   120+R P payload
inline constexpr std::size_t kEntryHeaderSize = 120;
// Entries larger than this are refused on both sides (a .lsnif is at most a few MiB).
inline constexpr std::uint64_t kMaxEntrySize = std::uint64_t(1) << 30;

}  // namespace lsnif::cache
