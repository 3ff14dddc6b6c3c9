// The cache on an HTTP(S) server, and a directory in front of it (docs/pipeline.md "A cache
// server").
//
// Remote speaks plain GET and PUT (libcurl) to URL/v1/entries/KK/KEY.entry, the directory
// store's layout under a URL, so any server that stores what is PUT and returns it on GET
// serves it: nginx with WebDAV PUT (examples/cache-server), an object store, a WebDAV share.
// Every fetched entry is verified (decode_entry: key, sizes, SHA-256) before use; a damaged,
// truncated or foreign response is `corrupt`, never a hit. A server that cannot be asked
// (refused, timed out, answering 5xx or refusing reads) is `unavailable`: a miss and one
// warning, never a failure; after one such request the server is not asked again in this
// run (Remote is shared by a run's jobs, so one slow server costs one timeout, not one per
// object). A request is tried `attempts` times, `kRetryDelays` apart, each bounded by
// `timeout_seconds` (connecting included).
//
// Cache puts the levels together: `local` (a Store; the only level without a server), then
// `remote`. A hit on the server is copied into the local level.
//
// Contract: nothing here throws, exits or prints, and the token is never written anywhere
// (messages, reports, manifests); warnings come back through take_warnings(). Remote and
// Cache may be used from several threads at once.
#pragma once

#include <lsnif/cache/cache.hpp>

#include <atomic>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::cache {

// Seconds between the attempts of one request.
inline constexpr double kRetryDelays[] = {0.25, 0.5};

struct RemoteOptions {
    std::string url;  // http://HOST[:PORT]/PATH or https://...; no user:password, query or fragment
    double timeout_seconds = 10;  // per attempt, connecting included; (0, 3600]
    int attempts = 3;             // 1 + retries after a failure that may pass (5xx, timeout, refused)
    std::string token;            // bearer token sent with every request; empty: none
};

// Whether `location` (a --cache value) names a server rather than a directory: it starts with
// a URL scheme ("word://"). Only http:// and https:// are served (Remote::open says so).
bool is_url(std::string_view location);

class Remote {
public:
    // Checks the URL (scheme http or https, a host, no credentials, query or fragment) and
    // the options; asks the server nothing.
    static Result<Remote> open(const RemoteOptions& options);

    Lookup get(std::string_view key) const;
    // Stores under `key`. An error when the server refused or could not be reached (the
    // caller warns and goes on: the result exists locally).
    Result<void> put(std::string_view key, const Entry& entry) const;
    // Whether the server holds an intact entry for `key` (a GET verified like get()).
    bool has(std::string_view key) const { return get(key).status == Status::hit; }

    std::string entry_url(std::string_view key) const;
    const std::string& url() const { return url_; }
    // Why the server stopped being asked in this run ("" while it is asked).
    std::string down_reason() const;

private:
    struct Shared;  // the down flag and its reason, shared by copies
    Remote(RemoteOptions options, std::string url);
    RemoteOptions options_;
    std::string url_;  // without a trailing '/'
    std::shared_ptr<Shared> shared_;
};

struct CacheOptions {
    std::string location;    // --cache: a directory, or an http(s) URL
    std::string local;       // --cache-local DIR: a directory in front of a server; empty: none
    bool read_only = false;  // --cache-read-only: never write to the server (the local level still is)
    double timeout_seconds = 10;
    std::string token;  // LSNIF_CACHE_TOKEN
};

class Cache {
public:
    // A directory location is the local level itself (then `local` must be empty); a URL is
    // the remote level, with `local` in front when given. Refuses an unknown scheme
    // ("s3://..."), so that a URL is never taken for a directory name.
    static Result<Cache> open(const CacheOptions& options);

    // The local level first, then the server (its hit copied into the local level).
    Lookup get(std::string_view key) const;
    // Into the local level and, unless read-only, to the server: true when a level stored it,
    // false when none was to (read-only without a local level) or the server failed (a
    // warning, once), an error when the local level could not write it.
    Result<bool> put(std::string_view key, const Entry& entry) const;
    bool has(std::string_view key) const;

    // The directory store when the cache is a directory alone (what a Ninja plan needs: its
    // edges' outputs are entry files); null otherwise.
    const Store* directory() const { return remote_ ? nullptr : &*local_; }
    // Where the cache is, for reports: the directory or the URL (never the token).
    std::string describe() const;
    // Warnings collected since the last call (a server unavailable, a write refused), each once.
    std::vector<std::string> take_warnings() const;

private:
    void warn_once(const std::string& text) const;
    std::optional<Store> local_;
    std::optional<Remote> remote_;
    bool read_only_ = false;
    struct Notes;  // warnings and the write-refused flag, shared by copies
    std::shared_ptr<Notes> notes_;
};

}  // namespace lsnif::cache
