#!/usr/bin/python3
"""An independent reference of the .lsnif format, written from schema/FORMAT.md alone.

It reads a container (FORMAT.md §2-§7), answers rays with the inference of §8 and checks
the conformance vectors of §9. It shares no code, and no reading of code, with the C
reader. README.md lists what writing it found missing in the document, now settled there.

Readability comes first, like zstd's educational decoder: every rule is written where the
section it implements can be seen, and the comments cite those sections. Speed matters
only so far as the vector files take seconds: the walk of §8.4 is a plain loop per
ray, the feature encoding and the MLP run on NumPy arrays across all rays at once.

    lsnif_reference.py check ASSET.lsnif VECTORS.rays
    lsnif_reference.py check-all DIR          (every DIR/NAME.rays with DIR/NAME.lsnif)
    lsnif_reference.py trace ASSET.lsnif < rays   (8 numbers a line: o.x o.y o.z tmin d.x d.y d.z tmax)
    lsnif_reference.py info ASSET.lsnif
    lsnif_reference.py selftest

Needs Python 3.11, NumPy and python-zstandard (Debian: python3-numpy python3-zstandard).
"""

from __future__ import annotations

import math
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
import zstandard

F32 = np.float32
F64 = np.float64
INF = math.inf


# ---------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------

class LsnifError(Exception):
    """A file that breaks a rule of FORMAT.md. `status` is the name of §7.4 the rule
    gives, `offset` the file offset involved (None when none applies, as in §7.5)."""

    def __init__(self, path: str, status: str, message: str, offset: int | None = None):
        self.path, self.status, self.message, self.offset = path, status, message, offset
        where = "" if offset is None else f" (offset {offset})"
        super().__init__(f"{path}: {status}: {message}{where}")


# ---------------------------------------------------------------------------------------
# §3 CRC-32C, table driven
# ---------------------------------------------------------------------------------------

def _make_crc32c_table() -> tuple[int, ...]:
    """Entry b is the CRC register after shifting byte b through the bitwise loop of §3."""
    table = []
    for b in range(256):
        crc = b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC32C_TABLE = _make_crc32c_table()


def crc32c(data: bytes | memoryview) -> int:
    crc = 0xFFFFFFFF
    table = _CRC32C_TABLE
    for b in bytes(data):
        crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


# ---------------------------------------------------------------------------------------
# §2-§7 The container
# ---------------------------------------------------------------------------------------

SIGNATURE = bytes([0x8C, 0x4C, 0x53, 0x4E, 0x0D, 0x0A, 0x1A, 0x0A])
READER_VERSION = (1, 2)  # the version this reader implements (§2.2)
KNOWN_TAGS = (b"META", b"MODL", b"OCCU", b"GRID", b"MLPW")  # §6, also the order of E1
REQUIRED = 0x00000001
MAX_SECTION_RAW = 1 << 30
MAX_FILE_SIZE = 1 << 34
MAX_META_RAW = 1 << 20
ZSTD_WINDOW_MAX = 1 << 27
ZSTD_MAGIC = bytes([0x28, 0xB5, 0x2F, 0xFD])  # RFC 8878 §3.1.1, 0xFD2FB528 little-endian
GRID_FP16, GRID_U8_AFFINE = 0, 1
RAY_INPUT_DIRECTION, RAY_INPUT_ENTRY_OFFSETS = 1, 2


def zstd_compress_bound(raw_size: int) -> int:
    """§4.4: the largest zstd frame of raw_size bytes of content."""
    extra = (131072 - raw_size) >> 11 if raw_size < 131072 else 0
    return raw_size + (raw_size >> 8) + extra


@dataclass
class Section:
    index: int          # position in the table
    entry_offset: int   # file offset of the table entry
    tag: bytes
    flags: int
    compression: int
    payload_offset: int
    stored_size: int
    raw_size: int
    stored_crc32c: int
    raw_crc32c: int


@dataclass
class Model:
    """Everything §6 defines, decoded. Grid tables keep their stored form: float32 for an
    fp16 grid (converted exactly), the bytes q plus (scale, offset) per level for 8-bit."""
    path: str
    version: tuple[int, int]
    sections: list[Section]
    metadata: str
    V: int                       # grid_resolution
    H: int                       # max_points
    L: int                       # level_count
    F: int                       # features_per_level
    log2_table_size: int
    level_resolution: list[int]  # r_0 .. r_{L-1}
    N: int                       # hidden_layer_count
    hidden_width: list[int]      # w_0 .. w_{N-1}
    output_count: int
    M: int                       # material_count
    activation: int
    distance_encoding: int
    hash_primes: tuple[int, int, int]
    box_min: np.ndarray          # f32[3]
    box_max: np.ndarray          # f32[3]
    grid_encoding: int
    ray_inputs: int
    occupancy: np.ndarray        # bool[V^3], by linear voxel index (§6.3)
    level_entries: list[int]
    level_dense: list[bool]
    grid_levels: list[np.ndarray]        # [entries_l][F]: float32 (fp16 grid) or uint8
    grid_dequant: list[tuple[np.float32, np.float32]]  # (scale_l, offset_l), 8-bit grid only
    weights: list[np.ndarray] = field(default_factory=list)  # float32 [out_k][in_k]
    biases: list[np.ndarray] = field(default_factory=list)   # float32 [out_k]

    @property
    def T(self) -> int:
        return 1 << self.log2_table_size

    @property
    def input_width(self) -> int:
        """§6.5: in_0."""
        b0 = self.ray_inputs & RAY_INPUT_DIRECTION
        b1 = (self.ray_inputs & RAY_INPUT_ENTRY_OFFSETS) >> 1
        return self.H * self.L * self.F + 3 * b0 + self.H * b1


def level_entries(resolution: list[int], T: int) -> list[int]:
    """§6.4: a level is dense when its (r + 1)^3 vertices fit into T entries."""
    return [(r + 1) ** 3 if (r + 1) ** 3 <= T else T for r in resolution]


def grid_raw_size(encoding: int, L: int, F: int, entries: list[int]) -> int:
    """§6.4 and §6.4.1."""
    if encoding == GRID_FP16:
        return 2 * F * sum(entries)
    return 8 * L + F * sum(entries)


def layer_shapes(H, L, F, ray_inputs, hidden_width, output_count) -> list[tuple[int, int]]:
    """§6.5: (in_k, out_k) for k = 0..N."""
    b0 = ray_inputs & RAY_INPUT_DIRECTION
    b1 = (ray_inputs & RAY_INPUT_ENTRY_OFFSETS) >> 1
    ins = [H * L * F + 3 * b0 + H * b1] + list(hidden_width)
    outs = list(hidden_width) + [output_count]
    return list(zip(ins, outs))


def fp16_finite(raw: bytes) -> np.ndarray:
    """§1.2: finite when the exponent field is not all ones."""
    bits = np.frombuffer(raw, dtype="<u2")
    return (bits & 0x7C00) != 0x7C00


class _Reader:
    """Applies the checks of §7.2 in their order; the first failure is raised."""

    def __init__(self, data: bytes, path: str):
        self.data = data
        self.size = len(data)
        self.path = path

    def fail(self, status: str, message: str, offset: int | None = None):
        raise LsnifError(self.path, "LSNIF_ERR_" + status, message, offset)

    def u16(self, off):
        return struct.unpack_from("<H", self.data, off)[0]

    def u32(self, off):
        return struct.unpack_from("<I", self.data, off)[0]

    def u64(self, off):
        return struct.unpack_from("<Q", self.data, off)[0]

    # --- A. Signature and version -------------------------------------------------------

    def check_signature(self):
        d, size = self.data, self.size
        present = d[:min(size, 8)]
        if present == SIGNATURE[:len(present)]:
            if size < 8:
                self.fail("TRUNCATED", f"the file has {size} bytes, fewer than the 8-byte signature", 0)
            return
        if size >= 4 and d[1:4] == b"LSN":
            if d[0] == 0x0C:
                cause = "the high bit of byte 0 was stripped (7-bit transfer)"
            elif size >= 6 and d[4] == 0x0A:
                cause = "CR LF was converted to LF"
            elif size >= 6 and d[4:6] == b"\x0d\x0d":
                cause = "LF was converted to CR LF"
            elif size >= 8 and d[4:8] == b"\x0d\x0a\x1a\x0d":
                cause = "a lone LF was converted to CR LF"
            else:
                cause = "the signature bytes were altered in some other way"
            self.fail("TRANSFER_DAMAGE", f"damaged in transfer: {cause}; copy the file again in binary mode", 0)
        self.fail("NOT_LSNIF", "not an lsnif file (signature does not match)", 0)

    def check_version(self):
        if self.size < 12:
            self.fail("TRUNCATED", "the file ends before the 12-byte frozen prefix", 0)
        major, minor = self.u16(8), self.u16(10)
        r_major, r_minor = READER_VERSION
        if major > r_major:
            self.fail("VERSION_NEWER", f"format version {major}.{minor} was written by a newer lsnif; upgrade", 8)
        if major < r_major:
            self.fail("VERSION_OLDER", f"format version {major}.{minor} was written by an older lsnif; re-convert", 8)
        if minor > r_minor:
            self.fail("VERSION_NEWER", f"format version {major}.{minor} was written by a newer lsnif; upgrade", 10)
        self.version = (major, minor)

    # --- B. Header ----------------------------------------------------------------------

    def check_header(self):
        if self.size < 64:
            self.fail("TRUNCATED", "the file ends before the 64-byte header", 0)
        if self.u32(60) != crc32c(self.data[0:60]):
            self.fail("CHECKSUM", "header_crc32c does not match header bytes 0..59", 60)
        if self.u32(12) != 64:
            self.fail("LAYOUT", f"header_size is {self.u32(12)}, must be 64", 12)
        if self.u32(44) != 0:
            self.fail("RESERVED", "header_flags is not 0", 44)
        if any(self.data[48:60]):
            self.fail("RESERVED", "header bytes 48..59 are not zero", 48)
        if self.u32(36) != 64:
            self.fail("LAYOUT", f"entry_size is {self.u32(36)}, must be 64", 36)
        file_size = self.u64(16)
        if file_size > MAX_FILE_SIZE:
            self.fail("LIMIT", f"file_size {file_size} exceeds 2^34", 16)
        if self.size < file_size:
            self.fail("TRUNCATED", f"file_size says {file_size} bytes, the file has {self.size}", 16)
        if self.size > file_size:
            self.fail("LAYOUT", f"{self.size - file_size} bytes of trailing data after file_size", file_size)
        count = self.u32(32)
        if not 1 <= count <= 64:
            self.fail("LIMIT", f"section_count is {count}, must be 1..64", 32)
        table = self.u64(24)
        if table % 64 != 0 or table < 64 or table > file_size or file_size - table < 64 * count:
            self.fail("LAYOUT", f"the section table at {table} ({count} entries) is misplaced", 24)
        if self.u32(40) != crc32c(self.data[table:table + 64 * count]):
            self.fail("CHECKSUM", "table_crc32c does not match the section table", 40)
        self.file_size, self.table_offset, self.section_count = file_size, table, count

    # --- C. Section entries -------------------------------------------------------------

    def check_entries(self):
        self.sections = []
        seen = set()
        for i in range(self.section_count):
            at = self.table_offset + 64 * i
            tag = self.data[at:at + 4]
            if not all(0x21 <= b <= 0x7E for b in tag):
                self.fail("LAYOUT", f"entry {i}: tag {tag!r} is not four printable non-space characters", at)
            if tag in seen:
                self.fail("LAYOUT", f"entry {i}: tag {tag.decode()} appears twice", at)
            seen.add(tag)
            flags = self.u32(at + 4)
            if flags & ~REQUIRED:
                self.fail("RESERVED", f"section {tag.decode()}: undefined section_flags bits 0x{flags:08x}", at + 4)
            if any(self.data[at + 12:at + 16]) or any(self.data[at + 48:at + 64]):
                self.fail("RESERVED", f"section {tag.decode()}: reserved entry bytes are not zero", at)
            compression = self.u32(at + 8)
            if compression not in (0, 1):
                self.fail("LAYOUT", f"section {tag.decode()}: compression {compression} is not 0 or 1", at + 8)
            payload, stored, raw = self.u64(at + 16), self.u64(at + 24), self.u64(at + 32)
            if raw > MAX_SECTION_RAW:
                self.fail("LIMIT", f"section {tag.decode()}: raw_size {raw} exceeds 2^30", at + 32)
            if compression == 0 and stored != raw:
                self.fail("LAYOUT", f"section {tag.decode()}: uncompressed but stored_size {stored} "
                          f"!= raw_size {raw}", at + 24)
            if compression == 1 and not 1 <= stored <= zstd_compress_bound(raw):
                self.fail("LIMIT", f"section {tag.decode()}: zstd stored_size {stored} outside "
                          f"1..{zstd_compress_bound(raw)}", at + 24)
            if payload % 64 != 0 or payload > self.file_size or self.file_size - payload < stored:
                self.fail("LAYOUT", f"section {tag.decode()}: payload at {payload} ({stored} bytes) "
                          "is misplaced", at + 16)
            if tag not in KNOWN_TAGS and flags & REQUIRED:
                self.fail("UNKNOWN_REQUIRED", f"section {tag.decode()} is unknown and marked REQUIRED", at)
            self.sections.append(Section(i, at, tag, flags, compression, payload, stored, raw,
                                         self.u32(at + 40), self.u32(at + 44)))

    # --- D. Regions ---------------------------------------------------------------------

    def check_regions(self):
        regions = [(0, 64, "the header"),
                   (self.table_offset, self.table_offset + 64 * self.section_count, "the section table")]
        regions += [(s.payload_offset, s.payload_offset + s.stored_size, f"section {s.tag.decode()}")
                    for s in self.sections if s.stored_size != 0]
        regions.sort(key=lambda r: r[0])  # stable: the header stays first among equal starts
        end, previous = 0, None
        for start, stop, name in regions:
            if start < end:
                self.fail("LAYOUT", f"{name} overlaps {previous}", start)
            if any(self.data[end:start]):
                self.fail("RESERVED", f"padding before {name} is not zero", end)
            end, previous = stop, name
        if any(self.data[end:self.file_size]):
            self.fail("RESERVED", "padding after the last region is not zero", end)

    # --- §7.3 Decoding a payload --------------------------------------------------------

    def decode(self, s: Section) -> bytes:
        stored = self.data[s.payload_offset:s.payload_offset + s.stored_size]
        name = f"section {s.tag.decode()}"
        if crc32c(stored) != s.stored_crc32c:
            self.fail("CHECKSUM", f"{name}: stored_crc32c does not match", s.payload_offset)
        if s.compression == 0:
            raw = stored
        else:
            raw = self.zstd_decode(stored, s, name)
        if crc32c(raw) != s.raw_crc32c:
            self.fail("CHECKSUM", f"{name}: raw_crc32c does not match", s.payload_offset)
        return raw

    def zstd_decode(self, stored: bytes, s: Section, name: str) -> bytes:
        """§4.4: one frame, no dictionary, window <= 2^27, exactly raw_size bytes, nothing
        after it. The input goes in small pieces so that a hostile frame cannot produce
        much more output than raw_size before we notice (a zstd block decodes to at most
        128 KiB, so 64 input bytes can yield at most 8 MiB)."""
        # RFC 8878 calls two things frames; §4.4 asks for "one Zstandard frame", so a
        # skippable frame (magic 0x184D2A5?) is not one, even alone (README).
        if stored[:4] != ZSTD_MAGIC:
            self.fail("DECOMPRESS", f"{name}: the payload does not start with a Zstandard frame", s.payload_offset)
        try:
            if zstandard.get_frame_parameters(stored).dict_id != 0:
                self.fail("DECOMPRESS", f"{name}: the zstd frame needs a dictionary", s.payload_offset)
        except zstandard.ZstdError as e:
            self.fail("DECOMPRESS", f"{name}: bad zstd frame header: {e}", s.payload_offset)
        decoder = zstandard.ZstdDecompressor(max_window_size=ZSTD_WINDOW_MAX).decompressobj()
        out = bytearray()
        fed = 0
        try:
            while fed < len(stored) and not decoder.eof:
                out += decoder.decompress(stored[fed:fed + 64])
                fed += min(64, len(stored) - fed)
                if len(out) > s.raw_size:
                    self.fail("DECOMPRESS", f"{name}: the frame decodes to more than raw_size {s.raw_size} bytes",
                              s.payload_offset)
        except zstandard.ZstdError as e:
            self.fail("DECOMPRESS", f"{name}: zstd: {e}", s.payload_offset)
        if not decoder.eof:
            self.fail("DECOMPRESS", f"{name}: the zstd frame is incomplete", s.payload_offset)
        if decoder.unused_data or fed < len(stored):
            self.fail("DECOMPRESS", f"{name}: bytes left after the zstd frame", s.payload_offset)
        if len(out) != s.raw_size:
            self.fail("DECOMPRESS", f"{name}: the frame decodes to {len(out)} bytes, raw_size is {s.raw_size}",
                      s.payload_offset)
        return bytes(out)

    # --- E. Model -----------------------------------------------------------------------

    def build_model(self) -> Model:
        by_tag = {s.tag: s for s in self.sections}
        for tag in KNOWN_TAGS:  # E1
            if tag not in by_tag:
                self.fail("MISSING_SECTION", f"section {tag.decode()} is missing")
        modl = by_tag[b"MODL"]
        if modl.raw_size != 256:  # E2
            self.fail("MODEL", f"MODL raw_size is {modl.raw_size}, must be 256", modl.entry_offset + 32)
        desc = self.decode(modl)  # E3
        d = self.check_descriptor(desc, modl.payload_offset)  # E4

        entries = level_entries(d["level_resolution"], 1 << d["log2_table_size"])
        shapes = layer_shapes(d["H"], d["L"], d["F"], d["ray_inputs"], d["hidden_width"], d["output_count"])
        expected = {b"OCCU": (d["V"] ** 3 + 7) // 8,
                    b"GRID": grid_raw_size(d["grid_encoding"], d["L"], d["F"], entries),
                    b"MLPW": 2 * sum(o * i + o for i, o in shapes)}
        for tag, size in expected.items():  # E5
            if by_tag[tag].raw_size != size:
                self.fail("MODEL", f"{tag.decode()} raw_size is {by_tag[tag].raw_size}, the descriptor implies {size}",
                          by_tag[tag].entry_offset + 32)

        meta = by_tag[b"META"]
        if meta.raw_size > MAX_META_RAW:  # E6
            self.fail("LIMIT", f"META raw_size {meta.raw_size} exceeds 2^20", meta.entry_offset + 32)
        meta_raw = self.decode(meta)  # E7
        if b"\x00" in meta_raw:
            self.fail("MODEL", "META contains a NUL byte", meta.payload_offset)
        try:
            metadata = meta_raw.decode("utf-8", errors="strict")  # RFC 3629, as §6.1 asks
        except UnicodeDecodeError as e:
            self.fail("MODEL", f"META is not well-formed UTF-8 at byte {e.start}", meta.payload_offset)

        occu_raw = self.decode(by_tag[b"OCCU"])  # E8
        grid_raw = self.decode(by_tag[b"GRID"])
        mlpw_raw = self.decode(by_tag[b"MLPW"])
        for s in self.sections:  # E9
            if s.tag not in KNOWN_TAGS:
                self.decode(s)

        # E10: content
        V = d["V"]
        occupancy = np.unpackbits(np.frombuffer(occu_raw, np.uint8), bitorder="little")
        if occupancy[V ** 3:].any():
            self.fail("RESERVED", "unused high bits of the last OCCU byte are not zero")
        occupancy = occupancy[:V ** 3].astype(bool)

        L, F = d["L"], d["F"]
        grid_levels, grid_dequant = [], []
        if d["grid_encoding"] == GRID_FP16:
            base = 0
            for l, n in enumerate(entries):
                raw = grid_raw[2 * base:2 * (base + n * F)]
                if not fp16_finite(raw).all():
                    self.fail("NONFINITE", f"GRID level {l} holds a non-finite feature")
                grid_levels.append(np.frombuffer(raw, "<f2").astype(F32).reshape(n, F))
                base += n * F
        else:
            pairs = np.frombuffer(grid_raw[:8 * L], "<f4").astype(F32).reshape(L, 2)
            base = 8 * L
            for l, n in enumerate(entries):
                scale, offset = pairs[l]
                if not (np.isfinite(scale) and np.isfinite(offset)):
                    self.fail("NONFINITE", f"GRID level {l}: scale or offset is not finite")
                if not scale >= 0:
                    self.fail("MODEL", f"GRID level {l}: scale {scale} is negative")
                ends = dequantize(np.array([0, 255], np.uint8), scale, offset)
                if not np.isfinite(ends).all():
                    self.fail("NONFINITE", f"GRID level {l}: the dequantized byte 0 or 255 is not finite")
                grid_levels.append(np.frombuffer(grid_raw, np.uint8, n * F, base).reshape(n, F))
                grid_dequant.append((F32(scale), F32(offset)))
                base += n * F

        weights, biases = [], []
        at = 0
        for k, (n_in, n_out) in enumerate(shapes):
            w_raw = mlpw_raw[at:at + 2 * n_out * n_in]
            at += 2 * n_out * n_in
            b_raw = mlpw_raw[at:at + 2 * n_out]
            at += 2 * n_out
            if not fp16_finite(w_raw).all():
                self.fail("NONFINITE", f"MLPW layer {k} holds a non-finite weight")
            if not fp16_finite(b_raw).all():
                self.fail("NONFINITE", f"MLPW layer {k} holds a non-finite bias")
            weights.append(np.frombuffer(w_raw, "<f2").astype(F32).reshape(n_out, n_in))
            biases.append(np.frombuffer(b_raw, "<f2").astype(F32))

        return Model(path=self.path, version=self.version, sections=self.sections, metadata=metadata,
                     V=V, H=d["H"], L=L, F=F, log2_table_size=d["log2_table_size"],
                     level_resolution=d["level_resolution"], N=d["N"], hidden_width=d["hidden_width"],
                     output_count=d["output_count"], M=d["M"], activation=d["activation"],
                     distance_encoding=d["distance_encoding"], hash_primes=d["hash_primes"],
                     box_min=d["box_min"], box_max=d["box_max"], grid_encoding=d["grid_encoding"],
                     ray_inputs=d["ray_inputs"], occupancy=occupancy, level_entries=entries,
                     level_dense=[(r + 1) ** 3 <= (1 << d["log2_table_size"]) for r in d["level_resolution"]],
                     grid_levels=grid_levels, grid_dequant=grid_dequant, weights=weights, biases=biases)

    def check_descriptor(self, desc: bytes, base: int) -> dict:
        """§6.2 fields, checked in the order E4.1-E4.20 of §7.2."""
        u32 = lambda off: struct.unpack_from("<I", desc, off)[0]
        fail = lambda status, msg, off=None: self.fail(status, "MODL: " + msg, None if off is None else base + off)
        if u32(0) != 256:
            fail("MODEL", f"descriptor_size is {u32(0)}, must be 256", 0)
        L = u32(12)
        if not 1 <= L <= 8:
            fail("MODEL", f"level_count {L} outside 1..8", 12)
        if any(u32(24 + 4 * l) for l in range(L, 8)):
            fail("RESERVED", "unused level_resolution slots are not zero", 24 + 4 * L)
        N = u32(56)
        if not 1 <= N <= 8:
            fail("MODEL", f"hidden_layer_count {N} outside 1..8", 56)
        if any(u32(60 + 4 * k) for k in range(N, 8)):
            fail("RESERVED", "unused hidden_width slots are not zero", 60 + 4 * N)
        minor = self.version[1]
        reserved_from = {0: 144, 1: 148}.get(minor, 152)
        if any(desc[reserved_from:256]):
            fail("RESERVED", f"reserved descriptor bytes {reserved_from}..255 are not zero", reserved_from)
        grid_encoding = u32(144) if minor >= 1 else 0
        ray_inputs = u32(148) if minor >= 2 else 0
        if grid_encoding not in (0, 1):
            fail("MODEL", f"grid_encoding {grid_encoding} is not 0 or 1", 144)
        if ray_inputs & ~3:
            fail("MODEL", f"ray_inputs 0x{ray_inputs:x} has bits other than 0 and 1", 148)
        V, H, F, log2T = u32(4), u32(8), u32(16), u32(20)
        if not 1 <= V <= 256:
            fail("MODEL", f"grid_resolution {V} outside 1..256", 4)
        if not 1 <= H <= 64:
            fail("MODEL", f"max_points {H} outside 1..64", 8)
        if not 1 <= F <= 8:
            fail("MODEL", f"features_per_level {F} outside 1..8", 16)
        if not 4 <= log2T <= 24:
            fail("MODEL", f"log2_table_size {log2T} outside 4..24", 20)
        resolution = [u32(24 + 4 * l) for l in range(L)]
        for l, r in enumerate(resolution):
            if not 1 <= r <= 4096:
                fail("MODEL", f"level_resolution[{l}] = {r} outside 1..4096", 24 + 4 * l)
        widths = [u32(60 + 4 * k) for k in range(N)]
        for k, w in enumerate(widths):
            if not 1 <= w <= 1024:
                fail("MODEL", f"hidden_width[{k}] = {w} outside 1..1024", 60 + 4 * k)
        M = u32(96)
        if M > 4096:
            fail("MODEL", f"material_count {M} exceeds 4096", 96)
        if u32(100) != 0:
            fail("MODEL", f"activation {u32(100)} is not 0 (ReLU)", 100)
        if u32(104) not in (0, 1):
            fail("MODEL", f"distance_encoding {u32(104)} is not 0 or 1", 104)
        box_min = np.frombuffer(desc, "<f4", 3, 120).astype(F32)
        box_max = np.frombuffer(desc, "<f4", 3, 132).astype(F32)
        for a in range(3):
            if not (np.isfinite(box_min[a]) and np.isfinite(box_max[a])):
                fail("NONFINITE", f"box coordinate of axis {'xyz'[a]} is not finite", 120 + 4 * a)
            if not box_min[a] < box_max[a]:
                fail("MODEL", f"box_min >= box_max on axis {'xyz'[a]}", 120 + 4 * a)
        grid_size = grid_raw_size(grid_encoding, L, F, level_entries(resolution, 1 << log2T))
        if grid_size > MAX_SECTION_RAW:
            fail("MODEL", f"the GRID tables would take {grid_size} bytes, more than 2^30")
        if u32(92) != 5 + M:
            fail("MODEL", f"output_count {u32(92)} is not 5 + material_count ({5 + M})", 92)
        return dict(V=V, H=H, L=L, F=F, log2_table_size=log2T, level_resolution=resolution, N=N,
                    hidden_width=widths, output_count=u32(92), M=M, activation=u32(100),
                    distance_encoding=u32(104), hash_primes=(u32(108), u32(112), u32(116)),
                    box_min=box_min, box_max=box_max, grid_encoding=grid_encoding, ray_inputs=ray_inputs)


def parse_lsnif(data: bytes, path: str = "<memory>") -> Model:
    """Steps A-E of §7.2 on the bytes of a file; raises LsnifError on the first failure."""
    r = _Reader(data, path)
    r.check_signature()
    r.check_version()
    r.check_header()
    r.check_entries()
    r.check_regions()
    return r.build_model()


def read_lsnif(path: str) -> Model:
    try:
        size = os.path.getsize(path)
        if size > MAX_FILE_SIZE:  # §5.1: may be refused before parsing
            raise LsnifError(path, "LSNIF_ERR_LIMIT", f"the file has {size} bytes, more than 2^34")
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise LsnifError(path, "LSNIF_ERR_IO", str(e)) from None
    return parse_lsnif(data, path)


# ---------------------------------------------------------------------------------------
# §8.1 Binary32 arithmetic
# ---------------------------------------------------------------------------------------
#
# NumPy's float32 + - * / and sqrt are IEEE operations rounded once in binary32, and a
# float64 -> float32 cast rounds once to nearest even, subnormals included. Only the fused
# multiply-add needs work: NumPy 1.24 and Python 3.11 have none.

def _round_to_odd_sum(p: np.ndarray, c: np.ndarray) -> np.ndarray:
    """p + c in binary64 rounded to odd: the exact sum if representable, else whichever
    of its two binary64 neighbours has an odd last significand bit.

    Rounding to odd in 53 bits, then to nearest in 24 (or fewer, for subnormals), gives the
    correctly rounded result: the odd last bit stands for "something below the
    53rd bit", so a value that only looks like a binary32 midpoint after the first rounding
    can never be one. Rounding the sum to nearest in binary64 first would not do (the classic
    double-rounding error)."""
    s = p + c
    # TwoSum (Knuth): err is exactly (p + c) - s, barring overflow.
    pv = s - c
    cv = s - pv
    err = (p - pv) + (c - cv)
    s_even = (np.asarray(s).view(np.uint64) & np.uint64(1)) == 0
    inexact = (err != 0) & np.isfinite(s)
    # s is the nearest neighbour; the exact sum lies on err's side of it, and so does the
    # other neighbour, which is odd whenever s is even.
    toward = np.copysign(INF, err)
    return np.where(inexact & s_even, np.nextafter(s, toward), s)


def fma32(a, b, c) -> np.ndarray:
    """IEEE 754 fusedMultiplyAdd in binary32: a * b + c rounded once. Arrays broadcast.

    The product of two binary32 values has at most 48 significant bits and lies between
    2^-298 and 2^256, so it is exact in binary64."""
    with np.errstate(invalid="ignore", over="ignore"):
        p = np.asarray(a, F32).astype(F64) * np.asarray(b, F32).astype(F64)
        return _round_to_odd_sum(p, np.asarray(c, F32).astype(F64)).astype(F32)


def max32(a, b):
    """§8.1: b if a < b else a (a NaN second argument yields the first)."""
    return np.where(a < b, b, a)


def min32(a, b):
    """§8.1: b if b < a else a."""
    return np.where(b < a, b, a)


def clamp32(x, lo, hi):
    """§8.1: lo if x < lo, else hi if hi < x, else x."""
    return np.where(x < lo, lo, np.where(hi < x, hi, x))


def dequantize(q: np.ndarray, scale, offset) -> np.ndarray:
    """§6.4.1: v = RN(q * scale_l + offset_l), one fused rounding."""
    return fma32(np.asarray(q).astype(F32), F32(scale), F32(offset))


def f32_bits(x) -> int:
    return int(np.asarray(x, F32).view(np.uint32))


def bits_f32(b: int) -> np.float32:
    return np.array([b], np.uint32).view(F32)[0]


# ---------------------------------------------------------------------------------------
# §8 Inference
# ---------------------------------------------------------------------------------------

INVALID, MISS, OK = "invalid", "miss", "ok"  # the classification of §9 field 10


@dataclass
class Answer:
    """Everything §8.8 compares for one ray."""
    classification: str
    n: int = 0
    voxels: list[int] = field(default_factory=list)
    o0: np.float32 | None = None      # None when the network did not run
    hit: int = 0
    t: np.float32 = F32(INF)
    normal: tuple = (F32(0), F32(0), F32(0))  # a miss's normal is unspecified (§8.7)
    material: int = 0


@dataclass
class Point:
    """A recorded point of the walk (§8.4): enough to compute its entry coordinates."""
    t: float            # the entry, an f32 value held in a Python float
    voxel: int
    x: tuple[int, int, int]
    step: tuple[int, int, int]
    on_face: tuple[bool, bool, bool]  # step != 0 and enter[a] == t


class WalkError(RuntimeError):
    pass


class Inference:
    def __init__(self, model: Model):
        self.m = model
        V = model.V
        lo64, hi64 = model.box_min.astype(F64), model.box_max.astype(F64)
        # §8.1 derived constants
        self.cell64 = (hi64 - lo64) / V
        self.cell = (model.box_max - model.box_min) / F32(V)
        ext = hi64 - lo64
        self.D = F32(np.sqrt((ext[0] * ext[0] + ext[1] * ext[1]) + ext[2] * ext[2]))
        self.level_scale = [F32(F64(r) / V) for r in model.level_resolution]
        # 256 dequantized values per level of an 8-bit grid: the same fused operation as
        # §6.4.1 and §8.5 ask for, computed once.
        self.level_lut = [dequantize(np.arange(256), s, o) for s, o in model.grid_dequant]

    # --- §8.2 and §8.3, for all rays at once --------------------------------------------

    def prepare(self, o: np.ndarray, d: np.ndarray, tmin: np.ndarray, tmax: np.ndarray):
        V = self.m.V
        with np.errstate(all="ignore"):
            finite = np.isfinite(o).all(1) & np.isfinite(d).all(1) & ~np.isnan(tmin) & ~np.isnan(tmax)
            s = fma32(d[:, 2], d[:, 2], fma32(d[:, 1], d[:, 1], d[:, 0] * d[:, 0]))
            lo64 = self.m.box_min.astype(F64)
            go = ((o.astype(F64) - lo64) / self.cell64).astype(F32)
            gd = (d.astype(F64) / self.cell64).astype(F32)
            inv = np.where(gd == 0, F32(INF), F32(1) / gd).astype(F32)
            overflow = ((gd != 0) & np.isinf(inv)).any(1)  # a subnormal grid component, §8.2
            invalid = ~finite | ~((s > 0) & (s < F32(INF))) | (gd == 0).all(1) | overflow
            k = np.arange(V + 1, dtype=F32)
            planes = (k[None, None, :] - go[:, :, None]) * inv[:, :, None]  # plane(a, k), f32

            t_near, t_far = tmin.copy(), tmax.copy()
            miss = np.zeros(len(o), bool)
            for a in range(3):
                zero = gd[:, a] == 0
                miss |= zero & ((go[:, a] < 0) | (go[:, a] > V))
                t0, t1 = planes[:, a, 0], planes[:, a, V]
                swap = t0 > t1
                t0, t1 = np.where(swap, t1, t0), np.where(swap, t0, t1)
                t_near = np.where(zero, t_near, max32(t_near, t0))
                t_far = np.where(zero, t_far, min32(t_far, t1))
            miss |= ~(t_near <= t_far)
        return dict(invalid=invalid, miss=miss & ~invalid, s=s, go=go, gd=gd, planes=planes,
                    t_near=t_near.astype(F32), t_far=t_far.astype(F32))

    # --- §8.4 The walk, one ray -----------------------------------------------------------

    def walk(self, planes: np.ndarray, gd: np.ndarray, go: np.ndarray, t_near: float, t_far: float) -> list[Point]:
        """Every comparison below is between f32 values held exactly in Python floats;
        the walk computes nothing but plane(), which `planes` holds for k = 0..V."""
        m = self.m
        V, H, occ = m.V, m.H, m.occupancy
        P = [planes[a].tolist() for a in range(3)]
        x, step, enter, exit_ = [0, 0, 0], [0, 0, 0], [0.0] * 3, [0.0] * 3
        for a in range(3):
            if gd[a] > 0:
                step[a] = 1
                x[a] = next((k for k in range(V - 1, 0, -1) if P[a][k] <= t_near), 0)
                enter[a], exit_[a] = P[a][x[a]], P[a][x[a] + 1]
            elif gd[a] < 0:
                step[a] = -1
                x[a] = next((k for k in range(0, V - 1) if P[a][k + 1] <= t_near), V - 1)
                enter[a], exit_[a] = P[a][x[a] + 1], P[a][x[a]]
            else:
                fl = math.floor(float(go[a]))
                x[a] = 0 if fl < 0 else (V - 1 if V - 1 < fl else fl)
                enter[a], exit_[a] = -INF, INF
        points: list[Point] = []
        while True:
            e12 = enter[2] if enter[1] < enter[2] else enter[1]  # max(enter[1], enter[2])
            enter_all = e12 if enter[0] < e12 else enter[0]
            x12 = exit_[2] if exit_[2] < exit_[1] else exit_[1]  # min(exit[1], exit[2])
            exit_all = x12 if x12 < exit_[0] else exit_[0]
            t = enter_all if t_near < enter_all else t_near
            voxel = x[0] + V * (x[1] + V * x[2])
            if t <= t_far and t < exit_all and occ[voxel]:
                on_face = tuple(step[a] != 0 and enter[a] == t for a in range(3))
                points.append(Point(t, voxel, tuple(x), tuple(step), on_face))
                if len(points) == H:
                    return points
            if exit_all > t_far:
                return points
            stepped = False
            for a in range(3):
                if exit_[a] == exit_all:
                    stepped = True
                    x[a] += step[a]
                    if not 0 <= x[a] < V:
                        return points
                    enter[a] = exit_[a]
                    exit_[a] = P[a][x[a] + 1] if step[a] > 0 else P[a][x[a]]
            if not stepped:
                # Only possible when exit is NaN, which §8.2's validity rules exclude.
                raise WalkError("the walk of §8.4 makes no progress (exit is NaN)")

    # --- §8.5 Entry coordinates and the input vector -------------------------------------

    def entry_coordinates(self, pts_t, pts_x, pts_step, pts_face, gd, go):
        """§8.4 "Entry coordinates", for arrays of points: g[a] is the face's plane when
        the ray entered through it, else the ray's point clamped into the voxel."""
        x = pts_x.astype(F32)
        face_value = np.where(pts_step < 0, x + F32(1), x)
        free = clamp32(fma32(pts_t[:, None], gd, go), x, x + F32(1))
        return np.where(pts_face, face_value, free).astype(F32)

    def level_features(self, l: int, g: np.ndarray) -> np.ndarray:
        """§8.5 "Features of a point" for level l and points g [P][3]: returns [P][F]."""
        m = self.m
        r = m.level_resolution[l]
        s = g * self.level_scale[l]                                  # f32
        fl = np.floor(s)
        fl = np.where(fl >= r, F32(r - 1), fl)
        fl = np.where(fl < 0, F32(0), fl).astype(F32)
        w = clamp32(s - fl, F32(0), F32(1)).astype(F32)
        i = fl.astype(np.int64)
        # Each axis has two slots, coordinate i (factor 1 - w) and i + 1 (factor w); the
        # first is absent when w == 1, the second when w == 0, and then the one left has
        # factor exactly 1 (1 - 0 is exactly 1). Walking the 8 slots x fastest and
        # skipping the absent ones gives §8.5's corners in §8.5's order.
        factor = (F32(1) - w, w)
        present = (w != 1, w != 0)
        values = self.level_values(l)
        acc = np.zeros((len(g), m.F), F32)
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    d = (dx, dy, dz)
                    weight = (factor[dx][:, 0] * factor[dy][:, 1]) * factor[dz][:, 2]  # f32, in that order
                    ok = present[dx][:, 0] & present[dy][:, 1] & present[dz][:, 2]
                    X, Y, Z = (i[:, a] + d[a] for a in range(3))
                    e = self.entry_index(l, X, Y, Z)
                    acc = np.where(ok[:, None], fma32(weight[:, None], values(e), acc), acc)
        return acc

    def entry_index(self, l: int, X, Y, Z) -> np.ndarray:
        """§6.4: the entry of lattice vertex (X, Y, Z) of level l."""
        m = self.m
        if m.level_dense[l]:
            n = m.level_resolution[l] + 1
            return X + n * (Y + n * Z)
        p0, p1, p2 = (np.uint32(p) for p in m.hash_primes)
        h = (X.astype(np.uint32) * p0) ^ (Y.astype(np.uint32) * p1) ^ (Z.astype(np.uint32) * p2)  # wraps mod 2^32
        return (h & np.uint32(m.T - 1)).astype(np.int64)

    def level_values(self, l: int):
        """Feature vectors [P][F] of entries e of level l, as f32 (§6.4, §6.4.1)."""
        table = self.m.grid_levels[l]
        if self.m.grid_encoding == GRID_FP16:
            return lambda e: table[e]
        lut = self.level_lut[l]
        return lambda e: lut[table[e]]

    def input_vectors(self, rays: list[int], points: list[list[Point]], prep) -> np.ndarray:
        m = self.m
        H, L, F = m.H, m.L, m.F
        X = np.zeros((len(rays), m.input_width), F32)  # absent points' slots stay +0
        rows = np.array([row for row, pts in enumerate(points) for _ in pts], np.int64)
        slots = np.array([h for pts in points for h in range(len(pts))], np.int64)
        ray_of = np.array(rays, np.int64)[rows]
        flat = [p for pts in points for p in pts]
        t = np.array([p.t for p in flat], F32)
        px = np.array([p.x for p in flat], np.int64).reshape(-1, 3)
        pstep = np.array([p.step for p in flat], np.int64).reshape(-1, 3)
        pface = np.array([p.on_face for p in flat], bool).reshape(-1, 3)
        with np.errstate(all="ignore"):
            g = self.entry_coordinates(t, px, pstep, pface, prep["gd"][ray_of], prep["go"][ray_of])
            for l in range(L):
                feats = self.level_features(l, g)
                for f in range(F):
                    X[rows, (slots * L + l) * F + f] = feats[:, f]
            col = H * L * F
            if m.ray_inputs & RAY_INPUT_DIRECTION:
                length = np.sqrt(prep["s"][rays])
                X[:, col:col + 3] = prep["d"][rays] / length[:, None]
                col += 3
            if m.ray_inputs & RAY_INPUT_ENTRY_OFFSETS:
                g0 = g[np.arange(len(flat)) - slots]  # a ray's points are consecutive, slot 0 first
                e = (g - g0) * self.cell
                offset = np.sqrt(fma32(e[:, 2], e[:, 2], fma32(e[:, 1], e[:, 1], e[:, 0] * e[:, 0]))) / self.D
                X[rows, col + slots] = offset
        return X

    # --- §8.6 The MLP ---------------------------------------------------------------------

    def mlp(self, X: np.ndarray) -> np.ndarray:
        """acc = b; acc = fma(x[i], W[j][i], acc) for i in order: the chain over i is
        sequential, so we run it for all rays and all outputs j at once."""
        x = X
        with np.errstate(invalid="ignore", over="ignore"):
            for k, (W, b) in enumerate(zip(self.m.weights, self.m.biases)):
                x64 = x.astype(F64)
                W64 = W.astype(F64)
                acc = np.broadcast_to(b.astype(F64), (len(x), len(b))).copy()
                for i in range(W.shape[1]):
                    p = x64[:, i, None] * W64[None, :, i]  # exact
                    acc = _round_to_odd_sum(p, acc).astype(F32).astype(F64)
                out = acc.astype(F32)
                if k < self.m.N:
                    out = np.where(out > 0, out, F32(0)).astype(F32)  # ReLU: +0 unless acc > 0
                x = out
        return x

    # --- §8.7 The hit record, and the whole query --------------------------------------

    def trace(self, o, d, tmin, tmax) -> list[Answer]:
        o, d = np.asarray(o, F32).reshape(-1, 3), np.asarray(d, F32).reshape(-1, 3)
        tmin, tmax = np.asarray(tmin, F32).reshape(-1), np.asarray(tmax, F32).reshape(-1)
        prep = self.prepare(o, d, tmin, tmax)
        prep["d"] = d
        answers: list[Answer] = []
        evaluated, evaluated_points = [], []
        for r in range(len(o)):
            if prep["invalid"][r]:
                answers.append(Answer(INVALID))
                continue
            if prep["miss"][r]:
                answers.append(Answer(MISS))
                continue
            try:
                pts = self.walk(prep["planes"][r], prep["gd"][r], prep["go"][r],
                                float(prep["t_near"][r]), float(prep["t_far"][r]))
            except WalkError as e:
                raise WalkError(f"ray {r}: {e}") from None
            # §9 field 10: a walk that finds no point is a miss without the network.
            answers.append(Answer(OK if pts else MISS, len(pts), [p.voxel for p in pts]))
            if pts:
                evaluated.append(r)
                evaluated_points.append(pts)
        if not evaluated:
            return answers

        out = self.mlp(self.input_vectors(evaluated, evaluated_points, prep))
        with np.errstate(all="ignore"):
            self.hit_records(out, evaluated, evaluated_points, prep, d, answers)
        return answers

    def hit_records(self, out, rays, points, prep, d, answers):
        m = self.m
        dd = d[rays]
        dl = np.sqrt((dd[:, 0] * dd[:, 0] + dd[:, 1] * dd[:, 1]) + dd[:, 2] * dd[:, 2])
        t_near, t_far = prep["t_near"][rays], prep["t_far"][rays]
        o0, o1 = out[:, 0], out[:, 1]
        if m.distance_encoding == 0:
            t = t_near + o1 * (t_far - t_near)
        else:
            t0 = np.array([pts[0].t for pts in points], F32)
            t = t0 + (o1 * self.D) / dl
        t = clamp32(t, t_near, t_far).astype(F32)
        n = out[:, 2:5]
        nl = np.sqrt((n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1]) + n[:, 2] * n[:, 2])
        normal = np.where((nl > 0)[:, None], n / nl[:, None], -dd / dl[:, None]).astype(F32)
        for j, r in enumerate(rays):
            a = answers[r]
            a.o0 = o0[j]
            if o0[j] > 0:
                a.hit, a.t, a.normal = 1, t[j], tuple(normal[j])
                a.material = first_largest(out[j, 5:5 + m.M])
            else:
                a.hit, a.t = 0, F32(INF)


def first_largest(logits: np.ndarray) -> int:
    """§8.7: the smallest m whose logit no other logit exceeds; 0 when there is none."""
    for m in range(len(logits)):
        if not (logits > logits[m]).any():
            return m
    return 0


# ---------------------------------------------------------------------------------------
# §9 Conformance vectors
# ---------------------------------------------------------------------------------------

@dataclass
class Vector:
    line: int
    case: str
    o: tuple
    tmin: int
    d: tuple
    tmax: int
    classification: str
    n: int
    voxels: list[int]
    o0: int | None
    hit: int
    t: int
    normal: tuple
    material: int


def read_vectors(path: str) -> list[Vector]:
    with open(path, encoding="utf-8") as f:
        lines = f.read().split("\n")
    if lines[0] != "lsnif-conformance 1":
        raise ValueError(f"{path}: the first line is not 'lsnif-conformance 1'")
    vectors = []
    for number, text in enumerate(lines[1:], start=2):
        if not text:
            continue
        f = text.split(" ")
        if len(f) != 19:
            raise ValueError(f"{path}:{number}: {len(f)} fields, expected 19")
        h = lambda s: int(s, 16)
        vectors.append(Vector(
            line=number, case=f[0], o=(h(f[1]), h(f[2]), h(f[3])), tmin=h(f[4]),
            d=(h(f[5]), h(f[6]), h(f[7])), tmax=h(f[8]), classification=f[9], n=int(f[10]),
            voxels=[] if f[11] == "-" else [int(v) for v in f[11].split(",")],
            o0=None if f[12] == "-" else h(f[12]), hit=int(f[13]), t=h(f[14]),
            normal=(h(f[15]), h(f[16]), h(f[17])), material=int(f[18])))
    return vectors


FIELDS = ("classification", "n", "voxels", "o0", "hit", "t", "normal", "material")


def compare(v: Vector, a: Answer) -> dict[str, tuple[str, str] | None]:
    """The fields §8.8 names, each None (not compared: it does not apply to this ray) or
    (ours, theirs)."""
    fmt_bits = lambda x: "-" if x is None else f"{f32_bits(x):08x}"
    result = {
        "classification": (a.classification, v.classification),
        "n": (str(a.n), str(v.n)),
        "voxels": (",".join(map(str, a.voxels)) or "-", ",".join(map(str, v.voxels)) or "-"),
        "o0": None, "hit": (str(a.hit), str(v.hit)), "t": None, "normal": None, "material": None,
    }
    if a.o0 is not None or v.o0 is not None:  # evaluated by either side
        result["o0"] = (fmt_bits(a.o0), "-" if v.o0 is None else f"{v.o0:08x}")
    if a.hit or v.hit:
        result["t"] = (fmt_bits(a.t), f"{v.t:08x}")
        result["normal"] = (" ".join(fmt_bits(c) for c in a.normal), " ".join(f"{c:08x}" for c in v.normal))
        result["material"] = (str(a.material), str(v.material))
    return result


def check(asset: str, vectors_path: str, verbose: int = 10) -> bool:
    start = time.perf_counter()
    model = read_lsnif(asset)
    vectors = read_vectors(vectors_path)
    bits = lambda vals: np.array(vals, np.uint32).view(F32)
    o = bits([v.o for v in vectors])
    d = bits([v.d for v in vectors])
    tmin, tmax = bits([v.tmin for v in vectors]), bits([v.tmax for v in vectors])
    answers = Inference(model).trace(o, d, tmin, tmax)
    elapsed = time.perf_counter() - start

    name = os.path.basename(vectors_path)
    counts = {f: [0, 0] for f in FIELDS}  # field -> [matches, mismatches]
    shown = 0
    for v, a in zip(vectors, answers):
        for what, pair in compare(v, a).items():
            if pair is None:
                continue
            same = pair[0] == pair[1]
            counts[what][0 if same else 1] += 1
            if not same and shown < verbose:
                shown += 1
                print(f"  {name}:{v.line} ({v.case}): {what}: ours {pair[0]}, vector {pair[1]}")
    bad = sum(c[1] for c in counts.values())
    summary = ", ".join(f"{f} {c[0]}/{c[0] + c[1]}" for f, c in counts.items())
    print(f"{'ok  ' if bad == 0 else 'FAIL'} {name}: {len(vectors)} rays; matching {summary}; {elapsed:.1f} s")
    return bad == 0


def check_all(directory: str) -> bool:
    ok = selftest(quiet=True)
    names = sorted(f[:-5] for f in os.listdir(directory) if f.endswith(".rays"))
    if not names:
        print(f"no .rays files in {directory}")
        return False
    for name in names:
        ok &= check(os.path.join(directory, name + ".lsnif"), os.path.join(directory, name + ".rays"))
    return ok


# ---------------------------------------------------------------------------------------
# Self-test of the arithmetic
# ---------------------------------------------------------------------------------------

def round_to_f32(x: Fraction) -> np.float32:
    """The binary32 value nearest to the exact rational x, ties to even, subnormals kept.
    (A zero result is returned as +0: the tests below avoid exact zeros.)"""
    if x == 0:
        return F32(0)
    sign = -1 if x < 0 else 1
    x = abs(x)
    e = x.numerator.bit_length() - x.denominator.bit_length()  # 2^e <= x < 2^(e+2)
    if Fraction(2) ** e > x:
        e -= 1
    if Fraction(2) ** (e + 1) <= x:
        e += 1
    quantum = Fraction(2) ** (max(e, -126) - 23)  # spacing of binary32 values around x
    q, rest = divmod(x / quantum, 1)
    if rest > Fraction(1, 2) or (rest == Fraction(1, 2) and q % 2 == 1):
        q += 1
    value = q * quantum
    if value >= Fraction(2) ** 128:
        return F32(sign * INF)
    return F32(sign * float(value))


def selftest(quiet: bool = False) -> bool:
    failures = []

    def expect(what, got, want):
        if f32_bits(got) != f32_bits(want):
            failures.append(f"{what}: got {f32_bits(got):08x}, want {f32_bits(want):08x}")

    # §3's check values
    for data, want in ((b"123456789", 0xE3069283), (b"", 0), (bytes(32), 0x8A9136AA)):
        if crc32c(data) != want:
            failures.append(f"crc32c({data!r}) = {crc32c(data):08x}, want {want:08x}")

    # §6.4.1's worked example
    for q, want in ((200, 0x3F7FFFFF), (100, 0xB2C00000), (255, 0x3FC66666)):
        expect(f"dequantize({q})", dequantize(np.array([q]), F32(0.01), F32(-1))[0], bits_f32(want))

    # Cases where rounding the binary64 sum to binary32 (double rounding) goes wrong: the
    # exact result lies just beside a binary32 midpoint and binary64 rounds it onto it.
    # The last column says whether the naive computation fails, to show that it is tested.
    a = F32(2.0 ** -24 * (1 + 2.0 ** -12))
    b = F32(1 - 2.0 ** -12 + 2.0 ** -24)  # a * b = 2^-24 * (1 + 2^-36)
    tiny = F32(2.0 ** -75)
    cases = [
        (a, b, F32(1), 0x3F800001, True),                   # 1 + 2^-24 + 2^-60: up
        (-a, b, F32(-1), 0xBF800001, True),                 # the same, negated
        (-a, b, F32(1 + 2.0 ** -22), 0x3F800001, True),     # 1 + 2^-23 + 2^-24 - 2^-60: down
        (a, b, F32(1 + 2.0 ** -23), 0x3F800002, False),     # 1 + 2^-23 + 2^-24 + 2^-60: up
        (tiny, tiny, F32(2.0 ** -149), 0x00000002, False),  # 1.5 * 2^-149, a tie: to even
        (tiny, F32(2.0 ** -75 * (1 + 2.0 ** -23)), F32(0), 0x00000001, False),  # just above 2^-150
        (tiny, tiny, F32(0), 0x00000000, False),            # 2^-150, a tie: to +0
    ]
    for x, y, z, want, naive_fails in cases:
        naive = F32(F64(x) * F64(y) + F64(z))
        if (f32_bits(naive) != want) != naive_fails:
            failures.append(f"fma32 case {x!r}, {y!r}, {z!r}: the naive result {f32_bits(naive):08x} "
                            f"{'should' if naive_fails else 'should not'} differ")
        expect(f"fma32({x!r}, {y!r}, {z!r})", fma32(x, y, z), bits_f32(want))

    # Random operands against exact rational arithmetic, including subnormal results and
    # massive cancellation.
    rng = np.random.default_rng(12345)
    n = 3000
    def random_f32(exp_lo, exp_hi):
        mant = rng.integers(0, 1 << 23, n, dtype=np.uint32)
        exp = rng.integers(exp_lo, exp_hi, n, dtype=np.uint32)
        sign = rng.integers(0, 2, n, dtype=np.uint32) << 31
        return (sign | (exp << 23) | mant).view(F32)
    for lo, hi in ((100, 154), (50, 90), (20, 70), (0, 8)):
        x, y = random_f32(lo, hi), random_f32(lo, hi)
        # c near -x*y so that the sum cancels, or random
        z = np.where(rng.random(n) < 0.5, (-(x.astype(F64) * y.astype(F64))).astype(F32), random_f32(lo, hi))
        got = fma32(x, y, z)
        for i in range(n):
            exact = Fraction(float(x[i])) * Fraction(float(y[i])) + Fraction(float(z[i]))
            if exact == 0 or abs(exact) >= Fraction(2) ** 128:
                continue
            want = round_to_f32(exact)
            if f32_bits(got[i]) != f32_bits(want):
                failures.append(f"fma32({x[i]!r}, {y[i]!r}, {z[i]!r}) = {f32_bits(got[i]):08x}, "
                                f"want {f32_bits(want):08x}")
                break

    # §8.1's max, min and clamp with NaN
    nan = F32(np.nan)
    if not (max32(F32(1), nan) == 1 and np.isnan(max32(nan, F32(1))) and min32(F32(1), nan) == 1
            and np.isnan(min32(nan, F32(1))) and np.isnan(clamp32(nan, F32(0), F32(1)))):
        failures.append("max/min/clamp NaN rules")

    for f in failures:
        print("selftest: " + f)
    if not quiet or failures:
        print(f"{'ok  ' if not failures else 'FAIL'} selftest: CRC-32C, fma32, max/min/clamp")
    return not failures


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------

def info(path: str):
    m = read_lsnif(path)
    print(f"{path}: version {m.version[0]}.{m.version[1]}")
    for s in m.sections:
        print(f"  {s.tag.decode()}  flags {s.flags}  compression {s.compression}  at {s.payload_offset}  "
              f"stored {s.stored_size}  raw {s.raw_size}")
    print(f"  V {m.V}  H {m.H}  L {m.L}  F {m.F}  T 2^{m.log2_table_size}  r {m.level_resolution}  "
          f"dense {m.level_dense}")
    print(f"  hidden {m.hidden_width}  M {m.M}  input width {m.input_width}  distance_encoding "
          f"{m.distance_encoding}  grid_encoding {m.grid_encoding}  ray_inputs {m.ray_inputs}")
    print(f"  box {m.box_min.tolist()} .. {m.box_max.tolist()}  primes {m.hash_primes}  "
          f"occupied {int(m.occupancy.sum())}/{m.V ** 3}")


def trace_stdin(path: str):
    inference = Inference(read_lsnif(path))
    rows = [list(map(float, line.split())) for line in sys.stdin if line.strip()]
    if any(len(r) != 8 for r in rows):
        raise SystemExit("trace: every line needs 8 numbers: o.x o.y o.z tmin d.x d.y d.z tmax")
    if not rows:
        return
    r = np.array(rows, F64).astype(F32)
    for a in inference.trace(r[:, 0:3], r[:, 4:7], r[:, 3], r[:, 7]):
        n = a.normal if a.hit else (F32(0),) * 3
        print(a.hit, a.t, *n, a.material)


def main(argv: list[str]) -> int:
    usage = __doc__.split("\n\n")[2]
    try:
        if len(argv) == 3 and argv[0] == "check":
            return 0 if check(argv[1], argv[2]) else 1
        if len(argv) == 2 and argv[0] == "check-all":
            return 0 if check_all(argv[1]) else 1
        if len(argv) == 2 and argv[0] == "trace":
            trace_stdin(argv[1])
            return 0
        if len(argv) == 2 and argv[0] == "info":
            info(argv[1])
            return 0
        if len(argv) == 1 and argv[0] == "selftest":
            return 0 if selftest() else 1
    except (LsnifError, WalkError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(usage, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
