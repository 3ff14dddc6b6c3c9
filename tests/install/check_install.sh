#!/usr/bin/env bash
# The reader as a renderer's build meets it: installed, relocated, found by CMake or
# pkg-config from C and C++, linked static or shared (docs/packaging.md).
#
#   check_install.sh WORK_DIR REFERENCE_C REFERENCE_CPP REFERENCE_EMBREE build SOURCE_DIR NATIVE ASSET...
#       builds format/ and embree/ alone (LSNIF_READER_ONLY, LSNIF_EMBREE), static (no
#       LSNIF_SHARED), installs them with --prefix WORK_DIR/staged, moves the tree to
#       WORK_DIR/moved and checks every consumer against the moved tree. The shared install
#       (LSNIF_SHARED: the .so and the archive) is what the Debian packages hold;
#       scripts/check_packages checks it with the prefix mode below on /usr.
#   check_install.sh WORK_DIR REFERENCE_C REFERENCE_CPP REFERENCE_EMBREE prefix PREFIX KIND ASSET...
#       checks the consumers against an existing install (KIND: shared or static), e.g.
#       /usr after `apt-get install ./*.deb` (scripts/check_packages).
#
# The consumers are examples/c_reader/print_info.c (C) and tests/install/consumer.cpp (C++)
# of the reader, and examples/embree_scene/embree_scene.c (C) of the Embree companion;
# REFERENCE_C, REFERENCE_CPP and REFERENCE_EMBREE are the same programs built in the
# project's own tree, and every consumer built here must print what its reference prints,
# for every ASSET.
# Exit status is the truth.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
c_source=$(cd "$here/../../examples/c_reader" && pwd)/print_info.c
embree_source=$(cd "$here/../../examples/embree_scene" && pwd)/embree_scene.c
declare -A references
fail() {
    echo "check_install: $*" >&2
    exit 1
}

# Runs a consumer on every asset and compares with its reference's output.
expect_reference_output() {
    local consumer=$1 reference=$2 label=$3
    local asset
    for asset in "${assets[@]}"; do
        local want got
        want=$("$reference" "$asset") || fail "reference $reference failed on $asset"
        got=$("$consumer" "$asset") || fail "$label: $consumer failed on $asset"
        [[ $got == "$want" ]] || fail "$label: output on $asset differs:"$'\n'"$got"$'\n'"expected:"$'\n'"$want"
    done
    echo "ok: $label"
}

# Checks how a consumer binary reached the reader: through liblsnif_format.so.N or
# linked in (no dynamic dependency at all).
expect_linkage() {
    local consumer=$1 linkage=$2 label=$3
    local needed
    needed=$(readelf -d "$consumer" | grep NEEDED || true)
    if [[ $linkage == shared ]]; then
        grep -q 'liblsnif_format\.so\.[0-9]' <<<"$needed" || fail "$label: $consumer does not load liblsnif_format.so.N"
    else
        ! grep -q 'liblsnif_format' <<<"$needed" || fail "$label: $consumer loads the shared reader"
    fi
}

# The directory under PREFIX holding the reader: lib (GNUInstallDirs' default) or Debian's
# multiarch lib/<triplet> for a /usr install.
library_dir() {
    local prefix=$1 dir
    for dir in "$prefix/lib" "$prefix/lib/$(gcc -print-multiarch)" "$prefix/lib64"; do
        if [[ -f $dir/pkgconfig/lsnif.pc ]]; then
            echo "$dir"
            return
        fi
    done
    fail "$prefix: no lib*/pkgconfig/lsnif.pc under it"
}

# One CMake consumer project (c_project, cpp_project or embree_project) against PREFIX.
cmake_consumer() {
    local prefix=$1 project=$2 linkage=$3 out=$4
    local static_flag=OFF
    [[ $linkage == static ]] && static_flag=ON
    local args=(-S "$here/$project" -B "$out" -DCMAKE_BUILD_TYPE=Release -DLSNIF_USE_STATIC_LIBS=$static_flag)
    [[ $prefix == /usr ]] || args+=(-DCMAKE_PREFIX_PATH="$prefix")
    cmake "${args[@]}" >"$out.log" 2>&1 || { cat "$out.log" >&2; fail "$project ($linkage): configure failed"; }
    cmake --build "$out" >>"$out.log" 2>&1 || { cat "$out.log" >&2; fail "$project ($linkage): build failed"; }
}

# Every consumer against one installed tree. KIND shared: the install has the shared
# library (and the archive); static: the archive alone.
check_prefix() {
    local prefix=$1 kind=$2 work=$3
    mkdir -p "$work"
    local libdir
    libdir=$(library_dir "$prefix")
    local pc_dirs="$libdir/pkgconfig"

    # pkg-config resolves the prefix from the .pc file's own place.
    local pc_prefix
    pc_prefix=$(PKG_CONFIG_PATH=$pc_dirs pkg-config --variable=prefix lsnif)
    [[ $(cd "$pc_prefix" && pwd -P) == $(cd "$prefix" && pwd -P) ]] ||
        fail "$prefix: lsnif.pc's prefix is $pc_prefix"

    # CMake: C only and C++, the default target and the static one.
    local linkages=(static)
    [[ $kind == shared ]] && linkages=(shared static)
    local project linkage
    for project in c_project cpp_project; do
        for linkage in "${linkages[@]}"; do
            local out="$work/$project-$linkage"
            cmake_consumer "$prefix" "$project" "$linkage" "$out"
            local language=${project%_project}
            local exe="$out/lsnif_consumer_$language"
            expect_linkage "$exe" "$linkage" "$project ($linkage, $prefix)"
            expect_reference_output "$exe" "${references[$language]}" "CMake $project, $linkage library, $prefix"
        done
    done

    # Plain compiler lines with pkg-config, as a Makefile would write them.
    local flags
    flags=$(PKG_CONFIG_PATH=$pc_dirs pkg-config --cflags --libs lsnif)
    cc -std=c99 -o "$work/pc_c" "$c_source" $flags -lm || fail "cc with pkg-config --libs failed"
    c++ -std=c++17 -o "$work/pc_cpp" "$here/consumer.cpp" $flags || fail "c++ with pkg-config --libs failed"
    local linkage_plain=static
    [[ $kind == shared ]] && linkage_plain=shared
    local language
    for language in c cpp; do
        local exe="$work/pc_$language"
        expect_linkage "$exe" "$linkage_plain" "pkg-config $(basename "$exe")"
        LD_LIBRARY_PATH=$libdir expect_reference_output "$exe" "${references[$language]}" \
            "pkg-config $(basename "$exe") ($kind install, $prefix)"
    done
    # A fully static executable: pkg-config --static names everything the archive needs.
    flags=$(PKG_CONFIG_PATH=$pc_dirs pkg-config --static --cflags --libs lsnif)
    cc -std=c99 -static -o "$work/pc_c_static" "$c_source" $flags -lm ||
        fail "cc -static with pkg-config --static failed"
    expect_linkage "$work/pc_c_static" static "pkg-config --static"
    expect_reference_output "$work/pc_c_static" "${references[c]}" "pkg-config --static, -static executable ($prefix)"
    check_embree_consumers "$prefix" "$kind" "$work" "$libdir"
}

# The Embree companion (liblsnif_embree.a) in the same tree: find_package(lsnif COMPONENTS
# embree) and pkg-config lsnif-embree, from C, with the reader the install defaults to.
check_embree_consumers() {
    local prefix=$1 kind=$2 work=$3 libdir=$4
    [[ -f $libdir/pkgconfig/lsnif-embree.pc ]] || fail "$prefix: no lsnif-embree.pc next to lsnif.pc"
    local out="$work/embree_project"
    cmake_consumer "$prefix" embree_project "$kind" "$out"
    local exe="$out/lsnif_consumer_embree"
    readelf -d "$exe" | grep -q 'libembree3\.so' || fail "$exe does not load Embree"
    expect_linkage "$exe" "$kind" "embree_project ($kind, $prefix)"
    expect_reference_output "$exe" "${references[embree]}" "CMake embree_project, $kind reader, $prefix"
    local flags
    flags=$(PKG_CONFIG_PATH=$libdir/pkgconfig pkg-config --cflags --libs lsnif-embree)
    cc -std=c99 -o "$work/pc_embree" "$embree_source" $flags || fail "cc with pkg-config lsnif-embree failed"
    expect_linkage "$work/pc_embree" "$kind" "pkg-config pc_embree"
    LD_LIBRARY_PATH=$libdir expect_reference_output "$work/pc_embree" "${references[embree]}" \
        "pkg-config pc_embree ($kind install, $prefix)"
}

# The shared library exports the C API and nothing else, under its SONAME.
check_shared_library() {
    local lib=$1
    local soname
    soname=$(readelf -d "$lib" | sed -n 's/.*Library soname: \[\(.*\)\]/\1/p')
    [[ $soname =~ ^liblsnif_format\.so\.[0-9]+$ ]] || fail "$lib: SONAME is '$soname'"
    local exported
    exported=$(nm -D --defined-only "$lib" | awk '$2 != "A" {print $3}' | sed 's/@.*//')
    [[ -n $exported ]] || fail "$lib: exports nothing"
    local stray
    stray=$(grep -v '^lsnif_' <<<"$exported" || true)
    [[ -z $stray ]] || fail "$lib: exports more than the C API:"$'\n'"$stray"
    local api
    api=$(sed -n 's/^LSNIF_API [^(]*[ *]\(lsnif_[a-z_]*\)(.*/\1/p' "$source_dir/format/include/lsnif/lsnif.h" | sort)
    [[ $(sort <<<"$exported") == "$api" ]] ||
        fail "$lib: exported symbols differ from lsnif.h's LSNIF_API functions"
    echo "ok: $lib is $soname and exports the $(wc -l <<<"$api") C API functions only"
}

usage="usage: $0 WORK_DIR REFERENCE_C REFERENCE_CPP REFERENCE_EMBREE {build SOURCE_DIR NATIVE | prefix PREFIX KIND} ASSET..."
(($# >= 8)) || fail "$usage"
work=$1 mode=$5
references=([c]=$2 [cpp]=$3 [embree]=$4)
assets=("${@:8}")
rm -rf "$work"
mkdir -p "$work"
case $mode in
build)
    source_dir=$6 native=$7
    build="$work/build"
    cmake -S "$source_dir" -B "$build" -DCMAKE_BUILD_TYPE=Release -DLSNIF_READER_ONLY=ON -DLSNIF_EMBREE=ON \
        -DLSNIF_SHARED=OFF -DLSNIF_NATIVE="$native" >"$build.log" 2>&1 ||
        { cat "$build.log" >&2; fail "configure of the reader failed"; }
    cmake --build "$build" -j 2 >>"$build.log" 2>&1 || { cat "$build.log" >&2; fail "build failed"; }
    cmake --install "$build" --prefix "$work/staged" >>"$build.log" 2>&1 || fail "install failed"
    # Relocation: nothing may remember where the tree was installed.
    mv "$work/staged" "$work/moved"
    if grep -rq "$work/staged" "$work/moved"; then
        fail "the installed tree names its install prefix: $(grep -rl "$work/staged" "$work/moved")"
    fi
    ! find "$work/moved" -name 'liblsnif_format.so*' | grep -q . || fail "static install has a .so"
    check_prefix "$work/moved" static "$work/consumers"
    ;;
prefix)
    prefix=$6 kind=$7
    source_dir=$(cd "$here/../.." && pwd)
    if [[ $kind == shared ]]; then
        check_shared_library "$(find "$(library_dir "$prefix")" -maxdepth 1 -name 'liblsnif_format.so.*.*' -print -quit)"
    fi
    check_prefix "$prefix" "$kind" "$work"
    ;;
*)
    fail "$usage"
    ;;
esac
echo "check_install: all consumers agree with the reference"
