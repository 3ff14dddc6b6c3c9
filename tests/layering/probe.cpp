// A translation unit that includes one header, LSNIF_PROBE_HEADER, and is compiled with one
// module's usage requirements alone (tests/CMakeLists.txt, the layering tests): it builds
// when the header is the module's own or below it, and fails to find it when it lies above
// (docs/architecture.md §2).
#include LSNIF_PROBE_HEADER

int lsnif_layering_probe() {
    return 0;
}
