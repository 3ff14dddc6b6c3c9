#!/usr/bin/env python3
"""The byte layout of schema/FORMAT.md checked by a reader that shares no code with
lsnif's: header (§4.1), signature (§4.1.1), CRC-32C (§3), section table (§4.2), placement
(§4.3), zstd payloads (§4.4, decoded by the zstd command) and the raw section sizes of the
worked example (§6.6) on the golden file tests/data/valid/v1_default.lsnif, which holds
that model. Exit 0 when every rule holds; otherwise one line per broken rule.

usage: read_format.py FILE.lsnif...
"""
import struct
import subprocess
import sys


def crc32c(data: bytes) -> int:
    """CRC-32C bit by bit, as FORMAT.md §3 defines it."""
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def main(path: str) -> int:
    problems = []

    def rule(ok: bool, what: str) -> None:
        if not ok:
            problems.append(what)

    rule(crc32c(b"123456789") == 0xE3069283, "CRC-32C check value (§3)")
    rule(crc32c(bytes(32)) == 0x8A9136AA, "CRC-32C of 32 zero bytes (§3)")
    data = open(path, "rb").read()
    rule(data[:8] == bytes([0x8C, 0x4C, 0x53, 0x4E, 0x0D, 0x0A, 0x1A, 0x0A]), "signature (§4.1.1)")
    (major, minor, header_size, file_size, table_offset, count, entry_size, table_crc, flags) = struct.unpack_from(
        "<HHIQQIIII", data, 8)
    rule(major == 1 and minor in (0, 1, 2), f"version {major}.{minor} (§4.1)")
    rule(header_size == 64 and entry_size == 64, "header and entry sizes 64 (§4.1)")
    rule(file_size == len(data), f"file_size {file_size} is the file's {len(data)} bytes (§4.1)")
    rule(table_offset % 64 == 0 and table_offset >= 64, "table_offset a multiple of 64, at least 64 (§4.1)")
    rule(1 <= count <= 64, "section_count 1..64 (§4.1)")
    rule(flags == 0 and data[48:60] == bytes(12), "header flags and reserved bytes zero (§4.1)")
    rule(struct.unpack_from("<I", data, 60)[0] == crc32c(data[:60]), "header_crc32c (§4.1)")
    table = data[table_offset:table_offset + 64 * count]
    rule(crc32c(table) == table_crc, "table_crc32c (§4.1)")
    raw_sizes = {}
    end_of_previous = table_offset + 64 * count
    for i in range(count):
        entry = table[64 * i:64 * (i + 1)]
        tag = entry[:4].decode("ascii", "replace")
        (section_flags, compression, reserved, offset, stored_size, raw_size, stored_crc,
         raw_crc) = struct.unpack_from("<IIIQQQII", entry, 4)
        rule(all(0x21 <= b <= 0x7E for b in entry[:4]), f"{tag}: tag printable (§4.2)")
        if tag in ("META", "MODL", "OCCU", "GRID", "MLPW"):
            rule(section_flags == 1, f"{tag}: REQUIRED flag on a v1 section (§4.2, §6)")
        else:
            rule(section_flags in (0, 1), f"{tag}: flags other than REQUIRED (§4.2)")
        rule(reserved == 0 and entry[48:] == bytes(16), f"{tag}: reserved fields zero (§4.2)")
        rule(offset % 64 == 0 and offset >= end_of_previous, f"{tag}: payload aligned, after what precedes it (§4.3)")
        end_of_previous = offset + stored_size
        stored = data[offset:offset + stored_size]
        rule(crc32c(stored) == stored_crc, f"{tag}: stored_crc32c (§4.2)")
        if compression == 0:
            raw = stored
            rule(stored_size == raw_size, f"{tag}: uncompressed stored_size = raw_size (§4.4)")
        elif compression == 1:
            bound = raw_size + (raw_size >> 8) + ((131072 - raw_size) >> 11 if raw_size < 131072 else 0)
            rule(1 <= stored_size <= bound, f"{tag}: stored_size within ZSTD_compressBound (§4.4)")
            raw = subprocess.run(["zstd", "-d", "-q", "-c"], input=stored, capture_output=True, check=True).stdout
        else:
            rule(False, f"{tag}: compression {compression} (§4.4)")
            continue
        rule(len(raw) == raw_size and crc32c(raw) == raw_crc, f"{tag}: raw bytes and raw_crc32c (§4.2)")
        raw_sizes[tag] = raw_size
    rule(data[end_of_previous:] == bytes(len(data) - end_of_previous), "only zero padding after the last payload (§4)")
    # The worked example of §6.6: the v1 model's raw section sizes and the first payload.
    if path.endswith("v1_default.lsnif"):
        for tag, size in (("MODL", 256), ("OCCU", 4096), ("GRID", 1572864), ("MLPW", 62218)):
            rule(raw_sizes.get(tag) == size, f"worked example: {tag} raw size {raw_sizes.get(tag)}, §6.6 says {size}")
        first = min(struct.unpack_from("<Q", table, 64 * i + 16)[0] for i in range(count))
        rule(table_offset == 64 and count == 5 and first == 384,
             "worked example: the table at 64..383 and the first payload at 384 (§6.6)")
    for p in problems:
        print(f"{path}: {p}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(max(main(p) for p in sys.argv[1:]))
