// The one translation unit that compiles tinygltf's implementation (Debian's
// libtinygltf-dev ships the header; its shared library is built with stb_image, which we
// do not want). Compiled into lsnif_scene so it is sanitized with the rest of the module,
// with image decoding and writing removed: the importer needs geometry only, and never
// decoding images removes stb_image from the attack surface of untrusted scenes.
// TINYGLTF_NO_STB_IMAGE, TINYGLTF_NO_STB_IMAGE_WRITE and TINYGLTF_NO_EXTERNAL_IMAGE are
// defined for the whole library by CMakeLists.txt so every TU sees the same declarations.
#define TINYGLTF_IMPLEMENTATION
#include <tiny_gltf.h>
