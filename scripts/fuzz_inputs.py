"""Seed inputs and mutations for the fuzzer (``scripts/fuzz.py``,
docs/fuzzing.md).

Seeds are tiny, deterministic datasets of every input form rotcal reads: CSV
dialects, MCAP with CDR and JSON messages, ``dataset.toml``, the run
configuration and the simulator's request. A mutation takes the bytes of one
file and a random generator and returns new bytes; a *neutral* mutation
leaves the samples as they were (a comment, a reordered table, a dropped
index), so the result must equal the seed's. MCAP mutations parse the record
layout (top-level records, a chunk's records, message indexes) and set the
length fields to extremes, not only random bytes.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import zstandard

MAGIC = b"\x89MCAP0\r\n"
FOOTER, CHUNK, MESSAGE, MESSAGE_INDEX, METADATA, DATA_END = 0x02, 0x06, 0x05, 0x07, 0x0C, 0x0F
SCHEMA, CHANNEL = 0x03, 0x04
EXTREMES = (0, 1, 8, 2**31 - 1, 2**32 - 1, 2**62, 2**63 - 1, 2**64 - 1)
HOSTILE_TEXT = (b"\x00", b"\n", b"\r", b"\x1b[31m", b"*", b"lot[1]", b"?", b"nan", b"NaN", b"-nan", b"inf", b"-Infinity",
                b"1e308", b"-1e308", b"1e999", b"1e12", b"-1e15", b"9" * 400, b"-9223372036854775809", b"\xff\xfe",
                b'"', b"", b" ", b"\t", b":x:", b"[bold]", b"0x10", b"1_0", b"\xc3\x28", b"-0", b"1e-320")
HOSTILE_TOML = ("nan", "+inf", "-inf", "1e308", "-1e308", "9" * 5000, "-9223372036854775809", '"a\\u0000b"', '"x\\ny"',
                '"\\u001b[31m"', '"lot[1]"', '"*"', '"../../etc/passwd"', '"/etc/passwd"', "true", "0", "-1", "[]", "{}",
                "[" * 400 + "]" * 400, "{a=" * 300 + "1" + "}" * 300, '"' + "x" * 10000 + '"', "1979-05-27T07:32:00Z",
                "[1, 2, 3]", '["t", "u"]', "0.0", "1e-320", '""')
HOSTILE_JSON = (b"NaN", b"Infinity", b"-Infinity", b"1e999", b"1e300", b"-1e15", b"1e12", b'"s"', b"null", b"true",
                b"[]", b"{}", b"[" * 5000 + b"]" * 5000, b'{"a":' * 2000 + b"1" + b"}" * 2000, b"9" * 5000, b'"\\u0000"')
HOSTILE_DOUBLES = (float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 5e-324, 0.0, 1e15, 1e16)


@dataclass(frozen=True)
class Mutation:
    name: str
    apply: Callable[[bytes, np.random.Generator], bytes]
    neutral: bool = False


def pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


# -- bytes of any file -------------------------------------------------------------

def bit_flips(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        if out:
            out[int(rng.integers(len(out)))] ^= 1 << int(rng.integers(8))
    return bytes(out)


def truncate(data: bytes, rng: np.random.Generator) -> bytes:
    return data[: int(rng.integers(len(data) + 1))]


def duplicate_span(data: bytes, rng: np.random.Generator) -> bytes:
    a = int(rng.integers(len(data) + 1))
    b = min(len(data), a + int(rng.integers(1, 4096)))
    return data[:b] + data[a:b] + data[b:]


def hostile_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    a = int(rng.integers(len(data) + 1))
    return data[:a] + pick(rng, HOSTILE_TEXT) + data[a + int(rng.integers(0, 8)):]


BYTES = (Mutation("bit_flips", bit_flips), Mutation("truncate", truncate), Mutation("duplicate_span", duplicate_span),
         Mutation("hostile_bytes", hostile_bytes))


# -- CSV ---------------------------------------------------------------------------

def _lines(data: bytes) -> tuple[list[bytes], list[int]]:
    """The lines and the indexes of the data rows (not comments, not blank,
    not the first non-comment line, which is a header or a row alike)."""
    lines = data.split(b"\n")
    content = [i for i, line in enumerate(lines) if line.strip() and not line.startswith(b"#")]
    return lines, content[1:]


def _with_row(edit: Callable[[list[bytes], list[int], np.random.Generator], None]):
    def apply(data: bytes, rng: np.random.Generator) -> bytes:
        lines, rows = _lines(data)
        if rows:
            edit(lines, rows, rng)
        return b"\n".join(lines)
    return apply


def _cell(lines, rows, rng):
    i = pick(rng, rows)
    sep = b";" if b";" in lines[i] else b"\t" if b"\t" in lines[i] else b","
    cells = lines[i].split(sep)
    cells[int(rng.integers(len(cells)))] = pick(rng, HOSTILE_TEXT)
    lines[i] = sep.join(cells)


def _dup_row(lines, rows, rng):
    i = pick(rng, rows)
    lines.insert(i, lines[i])


def _swap_rows(lines, rows, rng):
    i, j = pick(rng, rows), pick(rng, rows)
    lines[i], lines[j] = lines[j], lines[i]


def _drop_row(lines, rows, rng):
    del lines[pick(rng, rows)]


def _comment(lines, rows, rng):
    lines.insert(pick(rng, rows), b"# " + pick(rng, HOSTILE_TEXT).replace(b"\n", b"").replace(b"\r", b""))


def _blank(lines, rows, rng):
    lines.insert(pick(rng, rows), b"")


def _long_row(lines, rows, rng):
    lines[pick(rng, rows)] += pick(rng, (b",1", b" 1", b"1")) * int(rng.integers(1000, 400_000))


def _header(data: bytes, rng: np.random.Generator) -> bytes:
    lines = data.split(b"\n")
    first = next((i for i, line in enumerate(lines) if line.strip() and not line.startswith(b"#")), 0)
    lines[first] = lines[first].replace(pick(rng, (b"t", b"u", b"v", b"w", b"axis", b"rate_hz")), pick(rng, HOSTILE_TEXT), 1)
    return b"\n".join(lines)


def crlf(data: bytes, rng: np.random.Generator) -> bytes:
    return data.replace(b"\n", b"\r\n")


def permute_columns(data: bytes, rng: np.random.Generator) -> bytes:
    """The columns of a comma-separated file with a header in another order."""
    lines = data.split(b"\n")
    width = len(lines[0].split(b","))
    order = rng.permutation(width)
    out = []
    for line in lines:
        cells = line.split(b",")
        out.append(b",".join(cells[k] for k in order) if len(cells) == width else line)
    return b"\n".join(out)


CSV = (*BYTES, Mutation("csv_cell", _with_row(_cell)), Mutation("csv_duplicate_row", _with_row(_dup_row)),
       Mutation("csv_swap_rows", _with_row(_swap_rows)), Mutation("csv_drop_row", _with_row(_drop_row)),
       Mutation("csv_long_row", _with_row(_long_row)), Mutation("csv_header", _header),
       Mutation("csv_comment", _with_row(_comment), neutral=True), Mutation("csv_blank_line", _with_row(_blank), neutral=True),
       Mutation("csv_crlf", crlf, neutral=True))
CSV_WITH_HEADER = (*CSV, Mutation("csv_permute_columns", permute_columns, neutral=True))


# -- TOML --------------------------------------------------------------------------

_ASSIGN = re.compile(rb"^(\s*[A-Za-z0-9_\"-]+\s*=\s*)(.*)$", re.M)


def toml_value(data: bytes, rng: np.random.Generator) -> bytes:
    found = list(_ASSIGN.finditer(data))
    if not found:
        return data
    m = pick(rng, found)
    return data[: m.start(2)] + pick(rng, HOSTILE_TOML).encode() + data[m.end(2):]


def toml_duplicate_line(data: bytes, rng: np.random.Generator) -> bytes:
    lines = data.split(b"\n")
    i = int(rng.integers(len(lines)))
    lines.insert(i, lines[i])
    return b"\n".join(lines)


def toml_drop_line(data: bytes, rng: np.random.Generator) -> bytes:
    lines = data.split(b"\n")
    del lines[int(rng.integers(len(lines)))]
    return b"\n".join(lines)


def toml_comment(data: bytes, rng: np.random.Generator) -> bytes:
    lines = data.split(b"\n")
    lines.insert(int(rng.integers(len(lines) + 1)), b"# " + pick(rng, (b"lot[1]", b"*", b":x:", b"nan", b"[format]")))
    return b"\n".join(lines)


def toml_reorder_tables(data: bytes, rng: np.random.Generator) -> bytes:
    """The tables (``[name]`` and ``[[name]]`` blocks) in another order; the
    top-level keys before them stay first. The same document."""
    lines = data.split(b"\n")
    starts = [i for i, line in enumerate(lines) if line.startswith(b"[")]
    if not starts:
        return data
    blocks = [lines[a:b] for a, b in zip(starts, [*starts[1:], len(lines)])]
    arrays = {}  # an array of tables keeps its entries' order (it is a list)
    for block in blocks:
        arrays.setdefault(block[0].strip() if block[0].startswith(b"[[") else id(block), []).append(block)
    groups = list(arrays.values())
    order = rng.permutation(len(groups))
    return b"\n".join(lines[: starts[0]] + [line for k in order for block in groups[k] for line in block])


TOML = (*BYTES, Mutation("toml_value", toml_value), Mutation("toml_duplicate_line", toml_duplicate_line),
        Mutation("toml_drop_line", toml_drop_line), Mutation("toml_comment", toml_comment, neutral=True),
        Mutation("toml_reorder_tables", toml_reorder_tables, neutral=True))


# -- MCAP: the record layout -------------------------------------------------------

def mcap_records(data: bytes, start: int = 8) -> list[tuple[int, bytes]]:
    """(opcode, body) of each record from ``start`` (after the magic, or 0
    for a chunk's records), as far as they go."""
    out, pos = [], start
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((opcode, data[pos + 9 : pos + 9 + length]))
        pos += 9 + length
        if opcode == FOOTER and start:
            break
    return out


def join_records(records: list[tuple[int, bytes]]) -> bytes:
    return b"".join(struct.pack("<BQ", op, len(body)) + body for op, body in records)


def mcap_bytes(records: list[tuple[int, bytes]]) -> bytes:
    return MAGIC + join_records(records) + MAGIC


def open_chunk(body: bytes) -> tuple[tuple[int, int], bytes, bytes]:
    """((start, end) times, compression, decompressed records) of a chunk."""
    start, end, _, _ = struct.unpack_from("<QQQI", body)
    (n,) = struct.unpack_from("<I", body, 28)
    compression = body[32 : 32 + n]
    (length,) = struct.unpack_from("<Q", body, 32 + n)
    data = body[40 + n : 40 + n + length]
    raw = zstandard.ZstdDecompressor().decompress(data) if compression == b"zstd" else data
    return (start, end), compression, raw


def close_chunk(times: tuple[int, int], raw: bytes, compression: bytes = b"zstd", crc: int | None = None) -> bytes:
    data = zstandard.compress(raw) if compression == b"zstd" else raw
    return (struct.pack("<QQQI", *times, len(raw), zlib.crc32(raw) if crc is None else crc)
            + struct.pack("<I", len(compression)) + compression + struct.pack("<Q", len(data)) + data)


def _data_section(records):
    """The records up to DataEnd, with a footer that declares no summary
    (the summary's offsets are stale once a record moves)."""
    end = next((i for i, (op, _) in enumerate(records) if op == DATA_END), len(records) - 1)
    return [*records[:end], (DATA_END, struct.pack("<I", 0)), (FOOTER, struct.pack("<QQI", 0, 0, 0))]


def _reindexed(records, k: int, inner: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    """The chunk ``k`` with records ``inner`` and the message indexes after
    it rebuilt for them."""
    times, compression, _ = open_chunk(records[k][1])
    out = [*records[:k], (CHUNK, close_chunk(times, join_records(inner), compression))]
    j = k + 1
    channels = []
    while j < len(records) and records[j][0] == MESSAGE_INDEX:
        channels.append(struct.unpack_from("<H", records[j][1])[0])
        j += 1
    positions, pos = [], 0
    for _, body in inner:
        positions.append(pos)
        pos += 9 + len(body)
    for channel in channels:
        entries = b"".join(struct.pack("<QQ", struct.unpack_from("<Q", body, 6)[0], p)
                           for (op, body), p in zip(inner, positions) if op == MESSAGE and len(body) >= 14
                           and struct.unpack_from("<H", body)[0] == channel)
        out.append((MESSAGE_INDEX, struct.pack("<HI", channel, len(entries)) + entries))
    return _data_section(out + records[j:])


def _chunks(records) -> list[int]:
    return [i for i, (op, _) in enumerate(records) if op == CHUNK]


def _on_mcap(edit: Callable[[list, np.random.Generator], list | None]):
    """A mutation of the parsed records; the bytes unchanged when ``edit``
    finds nothing to change."""
    def apply(data: bytes, rng: np.random.Generator) -> bytes:
        records = mcap_records(data)
        changed = edit(records, rng) if records else None
        return data if changed is None else mcap_bytes(changed)
    return apply


def _patched(data: bytes, rng: np.random.Generator, offsets: list[tuple[int, str]]) -> bytes:
    pos, fmt = pick(rng, offsets)
    size = struct.calcsize(fmt)
    value = pick(rng, EXTREMES) % (1 << (8 * size))
    return data[:pos] + struct.pack(fmt, value) + data[pos + size:]


def record_length(data: bytes, rng: np.random.Generator) -> bytes:
    """A top-level record's length set to an extreme (the bytes unchanged)."""
    offsets, pos = [], 8
    for _, body in mcap_records(data):
        offsets.append((pos + 1, "<Q"))
        pos += 9 + len(body)
    return _patched(data, rng, offsets) if offsets else data


def _chunk_field(records, rng):
    chunks = _chunks(records)
    if not chunks:
        return None
    k = pick(rng, chunks)
    body = records[k][1]
    (n,) = struct.unpack_from("<I", body, 28)
    records[k] = (CHUNK, _patched(body, rng, [(16, "<Q"), (24, "<I"), (28, "<I"), (32 + n, "<Q")]))
    return records


def _inner(edit):
    """A mutation of one chunk's records (decompressed, edited, recompressed
    with a matching CRC so that the damage reaches the record parser)."""
    def chunk_edit(records, rng):
        chunks = _chunks(records)
        if not chunks:
            return None
        k = pick(rng, chunks)
        times, compression, raw = open_chunk(records[k][1])
        inner = mcap_records(raw, 0)
        messages = [i for i, (op, _) in enumerate(inner) if op == MESSAGE]
        if not messages:
            return None
        return edit(records, k, times, compression, raw, inner, messages, rng)
    return chunk_edit


def _inner_length(records, k, times, compression, raw, inner, messages, rng):
    starts = np.cumsum([0] + [9 + len(b) for _, b in inner])[:-1]
    pos = int(starts[pick(rng, range(len(inner)))])
    records[k] = (CHUNK, close_chunk(times, _patched(raw, rng, [(pos + 1, "<Q")]), compression))
    return records


def _value(records, k, times, compression, raw, inner, messages, rng):
    i = pick(rng, messages)
    op, body = inner[i]
    data = body[22:]
    if data.startswith(b"{"):
        fields = list(re.finditer(rb":\s*([^,}]+)", data))
        if not fields:
            return None
        m = pick(rng, fields)
        data = data[: m.start(1)] + pick(rng, HOSTILE_JSON) + data[m.end(1):]
    else:
        at = 4 + 8 * int(rng.integers(max(1, (len(data) - 12) // 8)))
        data = data[:at] + struct.pack("<d", pick(rng, HOSTILE_DOUBLES)) + data[at + 8:]
    inner[i] = (op, body[:22] + data)
    return _reindexed(records, k, inner)


def _changed_crc(records, k, times, compression, raw, inner, messages, rng):
    i = pick(rng, messages)
    body = bytearray(inner[i][1])
    body[-1] ^= 0x40
    inner[i] = (MESSAGE, bytes(body))
    old = struct.unpack_from("<I", records[k][1], 24)[0]
    records[k] = (CHUNK, close_chunk(times, join_records(inner), compression, crc=old))
    return records


def _duplicate_message(records, k, times, compression, raw, inner, messages, rng):
    i = pick(rng, messages)
    inner.insert(i, inner[i])
    return _reindexed(records, k, inner)


def _index_field(records, rng):
    indexes = [i for i, (op, _) in enumerate(records) if op == MESSAGE_INDEX]
    if not indexes:
        return None
    k = pick(rng, indexes)
    body = records[k][1]
    entries = (len(body) - 6) // 16
    offsets = [(2, "<I")] + [(6 + 16 * e + 8, "<Q") for e in range(min(entries, 64))]
    records[k] = (MESSAGE_INDEX, _patched(body, rng, offsets))
    return records


def _duplicate_record(records, rng):
    i = int(rng.integers(1, max(2, len(records) - 1)))
    records.insert(i, records[i])
    return records


def _swap_records(records, rng):
    data = _data_section(records)
    i, j = (int(rng.integers(1, len(data) - 2)) for _ in range(2))
    data[i], data[j] = data[j], data[i]
    return data


def _drop_summary(records, rng):
    return _data_section(records)


def _drop_indexes(records, rng):
    return _data_section([r for r in records if r[0] != MESSAGE_INDEX])


def _uncompressed(records, rng):
    for k in _chunks(records):
        times, _, raw = open_chunk(records[k][1])
        records[k] = (CHUNK, close_chunk(times, raw, b""))
    return _data_section(records)


def _definitions_first(records, rng):
    """The first chunk's schema and channel records copied to the top level
    before it, as a writer may put them."""
    chunks = _chunks(records)
    if not chunks:
        return None
    _, _, raw = open_chunk(records[chunks[0]][1])
    definitions = [r for r in mcap_records(raw, 0) if r[0] in (SCHEMA, CHANNEL)]
    return _data_section([records[0], *definitions, *records[1:]])


def _metadata(records, rng):
    text = [pick(rng, HOSTILE_TEXT) for _ in range(3)]
    pairs = b"".join(struct.pack("<I", len(t)) + t for t in text[1:])
    body = struct.pack("<I", len(text[0])) + text[0] + struct.pack("<I", len(pairs)) + pairs
    return _data_section([records[0], (METADATA, body), *records[1:]])


MCAP = (*BYTES, Mutation("mcap_record_length", record_length), Mutation("mcap_chunk_field", _on_mcap(_chunk_field)),
        Mutation("mcap_inner_length", _on_mcap(_inner(_inner_length))), Mutation("mcap_index_field", _on_mcap(_index_field)),
        Mutation("mcap_value", _on_mcap(_inner(_value))), Mutation("mcap_changed_crc", _on_mcap(_inner(_changed_crc))),
        Mutation("mcap_duplicate_message", _on_mcap(_inner(_duplicate_message))),
        Mutation("mcap_duplicate_record", _on_mcap(_duplicate_record)), Mutation("mcap_swap_records", _on_mcap(_swap_records)),
        Mutation("mcap_drop_summary", _on_mcap(_drop_summary), neutral=True),
        Mutation("mcap_drop_indexes", _on_mcap(_drop_indexes), neutral=True),
        Mutation("mcap_uncompressed", _on_mcap(_uncompressed), neutral=True),
        Mutation("mcap_definitions_first", _on_mcap(_definitions_first), neutral=True),
        Mutation("mcap_metadata", _on_mcap(_metadata), neutral=True))
