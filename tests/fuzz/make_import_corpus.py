#!/usr/bin/python3
"""Writes the seed corpus of fuzz_import (tests/fuzz/corpus/import): small valid and
slightly broken files of every importer, each prefixed with the byte that selects its
format in fuzz_import.cpp (0 .gltf, 1 .glb, 2 .obj, 3 .ply, 4 .off, 5 .stl). Hand-made
here, so the corpus holds no third-party data. Re-run after changing the format byte map."""
import base64
import json
import os
import struct

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "corpus", "import")
KIND = {"gltf": 0, "glb": 1, "obj": 2, "ply": 3, "off": 4, "stl": 5}

TET_P = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
TET_F = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]


def write(name, kind, body):
    if isinstance(body, str):
        body = body.encode()
    with open(os.path.join(OUT, name), "wb") as f:
        f.write(bytes([KIND[kind]]) + body)


def gltf_doc(index_type=5123, mode=4, extra=None, with_indices=True):
    pos = b"".join(struct.pack("<3f", *p) for p in TET_P)
    idx = b"".join(struct.pack("<3H", *f) for f in TET_F)
    buf = pos + idx
    prim = {"attributes": {"POSITION": 0}, "mode": mode}
    if with_indices:
        prim["indices"] = 1
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "children": [1], "translation": [1, 2, 3]},
                  {"mesh": 0, "rotation": [0, 0.7071068, 0, 0.7071068], "scale": [2, 2, 2]}],
        "meshes": [{"primitives": [prim]}],
        "buffers": [{"byteLength": len(buf)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 1]},
                      {"bufferView": 1, "componentType": index_type, "count": 12, "type": "SCALAR"}],
    }
    if extra:
        extra(doc)
    return doc, buf


def as_gltf(doc, buf):
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(buf).decode()
    return json.dumps(doc, separators=(",", ":"))


def as_glb(doc, buf):
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    buf += b"\0" * (-len(buf) % 4)
    chunks = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(buf), 0x004E4942) + buf
    return struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)) + chunks


def main():
    os.makedirs(OUT, exist_ok=True)
    for f in os.listdir(OUT):
        os.remove(os.path.join(OUT, f))
    d, b = gltf_doc()
    write("gltf_tet_hierarchy", "gltf", as_gltf(d, b))
    d, b = gltf_doc()
    write("glb_tet_hierarchy", "glb", as_glb(d, b))
    d, b = gltf_doc(mode=5)
    write("gltf_strip", "gltf", as_gltf(d, b))
    d, b = gltf_doc(with_indices=False)
    write("gltf_non_indexed", "gltf", as_gltf(d, b))

    def cycle(doc):
        doc["nodes"][1]["children"] = [0]
    d, b = gltf_doc(extra=cycle)
    write("gltf_node_cycle", "gltf", as_gltf(d, b))

    def draco(doc):
        doc["extensionsRequired"] = ["KHR_draco_mesh_compression"]
        doc["extensionsUsed"] = ["KHR_draco_mesh_compression"]
    d, b = gltf_doc(extra=draco)
    write("gltf_draco_required", "gltf", as_gltf(d, b))

    def missing_buffer(doc):
        doc["buffers"][0]["uri"] = "missing.bin"
    d, b = gltf_doc(extra=missing_buffer)
    write("gltf_missing_buffer", "gltf", json.dumps(d))

    def matrix_node(doc):
        doc["nodes"][1] = {"mesh": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 5, 0, 0, 1]}
    d, b = gltf_doc(extra=matrix_node)
    write("glb_matrix", "glb", as_glb(d, b))

    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in TET_P) + "vn 0 0 1\n" + \
        "".join(f"f {a + 1}//1 {b + 1}//1 {c + 1}//1\n" for a, b, c in TET_F) + "f 1 2 3 4\n"
    write("obj_tet_quad", "obj", obj)
    write("obj_negative_index", "obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    write("obj_out_of_range", "obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")

    ply_head = "ply\nformat {}\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n" \
               "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
    ply_ascii = ply_head.format("ascii 1.0") + "".join(f"{x} {y} {z}\n" for x, y, z in TET_P) + \
        "".join(f"3 {a} {b} {c}\n" for a, b, c in TET_F)
    write("ply_ascii_tet", "ply", ply_ascii)
    ply_bin = ply_head.format("binary_little_endian 1.0").encode() + \
        b"".join(struct.pack("<3f", *p) for p in TET_P) + b"".join(struct.pack("<B3i", 3, *f) for f in TET_F)
    write("ply_binary_tet", "ply", ply_bin)
    # Header lines the format allows where OpenMesh, reading words, would misread the body.
    lines = ply_head.format("binary_little_endian 1.0").split("\n")[:-1]
    lines.insert(1, "comment first")
    lines.insert(3, "obj_info element 9")
    lines.insert(-1, "comment last ")
    ply_crlf_notes = ("\r\n".join(lines) + "\r\n").encode() + \
        ply_bin[len(ply_head.format("binary_little_endian 1.0")):]
    write("ply_binary_tet_comments_crlf", "ply", ply_crlf_notes)

    off = "OFF\n# tetrahedron\n4 4 0\n" + "".join(f"{x} {y} {z}\n" for x, y, z in TET_P) + \
        "".join(f"3 {a} {b} {c}\n" for a, b, c in TET_F)
    write("off_tet", "off", off)
    write("off_nan", "off", "OFF\n3 1 0\n0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n")
    write("off_counts_too_large", "off", "OFF\n4000000000 1 0\n0 0 0\n")

    def normal(a, b, c):
        return (0.0, 0.0, 0.0)
    stl_ascii = "solid t\n" + "".join(
        "facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {TET_P[i][0]} {TET_P[i][1]} {TET_P[i][2]}\n" for i in f) +
        "endloop\nendfacet\n" for f in TET_F) + "endsolid t\n"
    write("stl_ascii_tet", "stl", stl_ascii)
    stl_bin = b"\0" * 80 + struct.pack("<I", len(TET_F)) + b"".join(
        struct.pack("<3f", *normal(*f)) + b"".join(struct.pack("<3f", *TET_P[i]) for i in f) + b"\0\0" for f in TET_F)
    write("stl_binary_tet", "stl", stl_bin)
    write("stl_binary_short", "stl", b"\0" * 80 + struct.pack("<I", 1000000))
    print(f"wrote {len(os.listdir(OUT))} seeds to {OUT}")


if __name__ == "__main__":
    main()
