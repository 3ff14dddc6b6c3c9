// The identity of the code that converts, for cache keys and manifests (docs/pipeline.md
// "Cache keys").
#include <lsnif/cache/cache.hpp>
#include <lsnif/converter/convert.hpp>

#include <embree3/rtcore.h>
#include <zstd.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <string>

namespace lsnif::converter {

namespace detail {
// Generated at build time by converter/convert/cmake/source_digest.cmake.
extern const char* const kSourceDigest;
extern const char* const kCompiler;
extern const char* const kCompileFlags;
}  // namespace detail

namespace {

// The Embree library this process runs (not the header it was compiled against: Debian may
// upgrade the shared library alone). "unknown" when no device can be made.
std::string embree_version() {
    RTCDevice device = rtcNewDevice("threads=1");
    if (!device) return "unknown";
    const std::string v = std::to_string(rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_VERSION));
    rtcReleaseDevice(device);
    return v;
}

ToolIdentity compute_identity() {
    ToolIdentity id;
    id.version = LSNIF_VERSION_STRING;
    id.sources = detail::kSourceDigest;
    id.compiler = detail::kCompiler;
    id.flags = detail::kCompileFlags;
    id.embree = embree_version();
    id.zstd = ZSTD_versionString();
    id.json = std::to_string(NLOHMANN_JSON_VERSION_MAJOR) + "." +
              std::to_string(NLOHMANN_JSON_VERSION_MINOR) + "." + std::to_string(NLOHMANN_JSON_VERSION_PATCH);
    cache::Sha256 h;
    h.update("lsnif-identity/1\n");
    for (const std::string* part :
         {&id.version, &id.sources, &id.compiler, &id.flags, &id.embree, &id.zstd, &id.json})
        h.update(*part).update("\n");
    id.digest = h.hex();
    return id;
}

}  // namespace

const ToolIdentity& tool_identity() {
    static const ToolIdentity id = compute_identity();
    return id;
}

std::string executable_path() {
    std::error_code ec;
    const std::filesystem::path p = std::filesystem::read_symlink("/proc/self/exe", ec);
    return ec ? std::string() : p.string();
}

}  // namespace lsnif::converter
