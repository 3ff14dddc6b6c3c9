// lsnif::cache on an HTTP(S) server (libcurl) and the two levels of Cache
// (lsnif/cache/remote.hpp has the contracts).
#include <lsnif/cache/remote.hpp>

#include <curl/curl.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <thread>

namespace lsnif::cache {

namespace {

// curl_global_init is not thread-safe: once per process, before any handle.
bool curl_ready() {
    static const bool ready = curl_global_init(CURL_GLOBAL_DEFAULT) == CURLE_OK;
    return ready;
}

// Why `url` cannot name a cache server; empty when it can.
std::string url_problem(const std::string& url) {
    const std::size_t scheme_end = url.find("://");
    const std::string scheme = scheme_end == std::string::npos ? "" : url.substr(0, scheme_end);
    if (scheme != "http" && scheme != "https")
        return "not an http:// or https:// URL (the cache is a directory or an HTTP(S) server)";
    const std::string rest = url.substr(scheme_end + 3);
    const std::string authority = rest.substr(0, rest.find('/'));
    if (authority.empty() || authority.front() == ':') return "no host";
    if (authority.find('@') != std::string::npos)
        return "credentials in the URL (give a bearer token in LSNIF_CACHE_TOKEN instead)";
    if (url.find_first_of("?#") != std::string::npos) return "a query or fragment in the URL";
    if (url.find_first_of(" \t\r\n") != std::string::npos) return "white space in the URL";
    const std::size_t colon = authority.rfind(':');
    if (colon != std::string::npos && authority.back() != ']') {
        const std::string port = authority.substr(colon + 1);
        if (port.empty() || port.size() > 5 || port.find_first_not_of("0123456789") != std::string::npos ||
            std::stoul(port) == 0 || std::stoul(port) > 65535)
            return "port '" + port + "' is not 1..65535";
    }
    return {};
}

// One HTTP exchange: what the transfer did and what the server said.
struct Exchange {
    CURLcode code = CURLE_OK;
    long status = 0;  // HTTP status; 0 when no response arrived
    std::vector<std::uint8_t> body;
    bool too_large = false;
    std::string error;  // libcurl's words for a transfer failure
};

struct Upload {
    const std::vector<std::uint8_t>* bytes;
    std::size_t offset = 0;
};

std::size_t on_body(char* data, std::size_t size, std::size_t count, void* user) {
    auto* ex = static_cast<Exchange*>(user);
    const std::size_t n = size * count;
    if (ex->body.size() + n > kMaxEntrySize + kEntryHeaderSize) {
        ex->too_large = true;
        return 0;  // aborts the transfer
    }
    ex->body.insert(ex->body.end(), data, data + n);
    return n;
}

std::size_t on_upload(char* buffer, std::size_t size, std::size_t count, void* user) {
    auto* up = static_cast<Upload*>(user);
    const std::size_t n = std::min(size * count, up->bytes->size() - up->offset);
    std::memcpy(buffer, up->bytes->data() + up->offset, n);
    up->offset += n;
    return n;
}

// GET `url` (upload null) or PUT `upload` to it, once.
Exchange exchange(const std::string& url, const RemoteOptions& o, const std::vector<std::uint8_t>* upload) {
    Exchange ex;
    CURL* h = curl_easy_init();
    if (!h) {
        ex.code = CURLE_FAILED_INIT;
        ex.error = "libcurl could not start a transfer";
        return ex;
    }
    char error[CURL_ERROR_SIZE] = {};
    const long timeout_ms = long(std::ceil(o.timeout_seconds * 1000));
    curl_slist* headers = nullptr;
    std::string auth;
    if (!o.token.empty()) {
        auth = "Authorization: Bearer " + o.token;
        headers = curl_slist_append(headers, auth.c_str());
    }
    Upload up{upload};
    curl_easy_setopt(h, CURLOPT_URL, url.c_str());
    curl_easy_setopt(h, CURLOPT_PROTOCOLS_STR, "http,https");
    curl_easy_setopt(h, CURLOPT_NOSIGNAL, 1L);  // timeouts without SIGALRM: safe in threads
    curl_easy_setopt(h, CURLOPT_CONNECTTIMEOUT_MS, timeout_ms);
    curl_easy_setopt(h, CURLOPT_TIMEOUT_MS, timeout_ms);
    curl_easy_setopt(h, CURLOPT_ERRORBUFFER, error);
    curl_easy_setopt(h, CURLOPT_USERAGENT, "lsnif-cache/1");
    if (headers) curl_easy_setopt(h, CURLOPT_HTTPHEADER, headers);
    curl_easy_setopt(h, CURLOPT_WRITEFUNCTION, on_body);
    curl_easy_setopt(h, CURLOPT_WRITEDATA, &ex);
    if (upload) {
        curl_easy_setopt(h, CURLOPT_UPLOAD, 1L);
        curl_easy_setopt(h, CURLOPT_READFUNCTION, on_upload);
        curl_easy_setopt(h, CURLOPT_READDATA, &up);
        curl_easy_setopt(h, CURLOPT_INFILESIZE_LARGE, curl_off_t(upload->size()));
    }
    ex.code = curl_easy_perform(h);
    curl_easy_getinfo(h, CURLINFO_RESPONSE_CODE, &ex.status);
    if (ex.code != CURLE_OK) ex.error = error[0] ? error : curl_easy_strerror(ex.code);
    curl_slist_free_all(headers);
    curl_easy_cleanup(h);
    return ex;
}

// Whether asking again may help: no answer, or the server's own trouble.
bool may_pass(const Exchange& ex) {
    if (ex.too_large) return false;
    return ex.code != CURLE_OK || ex.status >= 500 || ex.status == 429 || ex.status == 408;
}

std::string failure_text(const Exchange& ex) {
    if (ex.code != CURLE_OK) return ex.error;
    return "HTTP " + std::to_string(ex.status);
}

// The exchange, tried up to o.attempts times while a failure may pass.
Exchange with_retries(const std::string& url, const RemoteOptions& o,
                      const std::vector<std::uint8_t>* upload) {
    Exchange ex = exchange(url, o, upload);
    for (int attempt = 1; attempt < o.attempts && may_pass(ex); ++attempt) {
        const double delay = kRetryDelays[std::min<std::size_t>(attempt - 1, std::size(kRetryDelays) - 1)];
        std::this_thread::sleep_for(std::chrono::duration<double>(delay));
        ex = exchange(url, o, upload);
    }
    return ex;
}

}  // namespace

struct Remote::Shared {
    std::atomic<bool> down{false};
    std::mutex mutex;
    std::string reason;  // why it is down
};

bool is_url(std::string_view location) {
    const std::size_t sep = location.find("://");
    if (sep == std::string_view::npos || sep == 0) return false;
    for (std::size_t i = 0; i < sep; ++i) {
        const char c = location[i];
        const bool letter = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z');
        if (!(letter || (i > 0 && ((c >= '0' && c <= '9') || c == '+' || c == '-' || c == '.'))))
            return false;
    }
    return true;
}

Remote::Remote(RemoteOptions options, std::string url)
    : options_(std::move(options)), url_(std::move(url)), shared_(std::make_shared<Shared>()) {}

Result<Remote> Remote::open(const RemoteOptions& options) {
    if (std::string why = url_problem(options.url); !why.empty())
        return Error{"--cache " + options.url + ": " + why};
    if (!(options.timeout_seconds > 0 && options.timeout_seconds <= 3600))
        return Error{"--cache-timeout: expected seconds in (0, 3600]"};
    if (options.attempts < 1) return Error{"cache server: at least one attempt"};
    if (!curl_ready()) return Error{"--cache " + options.url + ": libcurl could not be initialized"};
    std::string url = options.url;
    while (url.back() == '/') url.pop_back();
    return Remote(options, url);
}

std::string Remote::entry_url(std::string_view key) const {
    return url_ + "/v1/entries/" + std::string(key.substr(0, 2)) + "/" + std::string(key) + ".entry";
}

std::string Remote::down_reason() const {
    std::lock_guard lock(shared_->mutex);
    return shared_->reason;
}

Lookup Remote::get(std::string_view key) const {
    Lookup out;
    if (!valid_key(key)) {
        out.status = Status::corrupt;
        out.problem = not_a_key(key);
        return out;
    }
    const std::string url = entry_url(key);
    if (shared_->down) {
        out.status = Status::unavailable;
        out.problem = url_ + ": " + down_reason();
        return out;
    }
    const Exchange ex = with_retries(url, options_, nullptr);
    if (ex.code == CURLE_OK && ex.status == 404) return out;  // a miss
    if (ex.code == CURLE_OK && ex.status == 200) {
        auto entry = decode_entry(ex.body, key);
        if (!entry) {
            out.status = Status::corrupt;
            out.problem = url + ": " + entry.error().message;
            return out;
        }
        out.status = Status::hit;
        out.entry = std::move(*entry);
        return out;
    }
    if (ex.too_large) {
        out.status = Status::corrupt;
        out.problem = url + ": larger than any entry (" + std::to_string(kMaxEntrySize) + " bytes)";
        return out;
    }
    // Down, slow, or refusing reads: every other key would fare the same.
    const std::string why =
        failure_text(ex) + (may_pass(ex) ? " (" + std::to_string(options_.attempts) + " attempts)" : "");
    {
        std::lock_guard lock(shared_->mutex);
        if (!shared_->down) shared_->reason = why;
        shared_->down = true;
    }
    out.status = Status::unavailable;
    out.problem = url_ + ": " + why;
    return out;
}

Result<void> Remote::put(std::string_view key, const Entry& entry) const {
    if (!valid_key(key)) return Error{not_a_key(key)};
    if (shared_->down) return Error{url_ + ": " + down_reason()};
    const std::vector<std::uint8_t> bytes = encode_entry(key, entry);
    const Exchange ex = with_retries(entry_url(key), options_, &bytes);
    if (ex.code == CURLE_OK && ex.status >= 200 && ex.status < 300) return {};
    const std::string why = failure_text(ex);
    if (may_pass(ex)) {
        std::lock_guard lock(shared_->mutex);
        if (!shared_->down) shared_->reason = why + " (" + std::to_string(options_.attempts) + " attempts)";
        shared_->down = true;
    }
    return Error{entry_url(key) + ": " + why};
}

struct Cache::Notes {
    std::mutex mutex;
    std::vector<std::string> pending;
    std::vector<std::string> said;
    std::atomic<bool> writes_refused{false};
};

Result<Cache> Cache::open(const CacheOptions& o) {
    Cache c;
    c.read_only_ = o.read_only;
    c.notes_ = std::make_shared<Notes>();
    if (is_url(o.location)) {
        auto remote = Remote::open({o.location, o.timeout_seconds, 3, o.token});
        if (!remote) return remote.error();
        c.remote_ = std::move(*remote);
        if (!o.local.empty()) {
            auto local = Store::open(o.local);
            if (!local) return Error{"--cache-local " + local.error().message};
            c.local_ = std::move(*local);
        }
        return c;
    }
    if (!o.local.empty())
        return Error{"--cache-local goes in front of a cache server: --cache is a directory"};
    if (o.location.empty()) return Error{"--cache: no directory or URL"};
    auto local = Store::open(o.location);
    if (!local) return local.error();
    c.local_ = std::move(*local);
    return c;
}

void Cache::warn_once(const std::string& text) const {
    std::lock_guard lock(notes_->mutex);
    if (std::find(notes_->said.begin(), notes_->said.end(), text) != notes_->said.end()) return;
    notes_->said.push_back(text);
    notes_->pending.push_back(text);
}

std::vector<std::string> Cache::take_warnings() const {
    std::lock_guard lock(notes_->mutex);
    return std::exchange(notes_->pending, {});
}

std::string Cache::describe() const {
    if (!remote_) return local_->root().parent_path().string();
    return remote_->url() + (local_ ? " (local level " + local_->root().parent_path().string() + ")" : "");
}

Lookup Cache::get(std::string_view key) const {
    Lookup local;
    if (local_) {
        local = local_->get(key);
        if (local.status == Status::hit || !remote_) return local;
    }
    Lookup remote = remote_->get(key);
    if (remote.status == Status::unavailable) {
        warn_once("the cache server is unavailable, converting here and not sharing the results: " +
                  remote.problem);
        return local.status == Status::corrupt ? local : remote;
    }
    if (remote.status == Status::hit) {
        if (local.status == Status::corrupt)
            warn_once("corrupt local cache entry replaced from the server: " + local.problem);
        if (local_) (void)local_->put(key, remote.entry);  // a local level that cannot write only costs speed
        return remote;
    }
    return local.status == Status::corrupt && remote.status == Status::miss ? local : remote;
}

Result<bool> Cache::put(std::string_view key, const Entry& entry) const {
    std::optional<Error> local_error;
    bool stored = false;
    if (local_) {
        auto r = local_->put(key, entry);
        stored = r.ok();
        if (!r) local_error = r.error();
    }
    if (remote_ && !read_only_ && !notes_->writes_refused) {
        auto r = remote_->put(key, entry);
        if (r) {
            stored = true;
        } else if (!remote_->down_reason().empty()) {
            warn_once("the cache server is unavailable, converting here and not sharing the results: " +
                      remote_->url() + ": " + remote_->down_reason());
        } else {
            notes_->writes_refused = true;  // a refusal (no token, a read-only server) holds for every key
            warn_once("the cache server refused to store a result, not asking it again in this run: " +
                      r.error().message);
        }
    }
    if (stored) return true;
    if (local_error) return *local_error;
    return false;
}

bool Cache::has(std::string_view key) const {
    if (local_ && local_->get(key).status == Status::hit) return true;
    return remote_ && remote_->has(key);
}

}  // namespace lsnif::cache
