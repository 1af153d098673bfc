"""MCAP ingest, messages per second: rotcal's ingest of a simulated capture
(``sensor_msgs/msg/Imu`` in CDR, zstd chunks; and JSON messages) against
two references measured in the same run:

- the path a user would write: ``mcap.reader.make_reader`` with the
  ``mcap_ros2`` decoder (json.loads for JSON), one message at a time into
  Python lists, decoding the DUT topic only;
- the decompression bound: zstd alone over the same chunks (already read
  into memory) into one buffer allocated beforehand, on the cores the run
  may use (``parallel.cores``): no file reading, no CRC, no decoding.

rotcal's figure includes everything ingest does (file reading, chunk CRCs,
the table channel mapped onto the samples, validation, canonical columns),
and, on its own line, the decoding into columns alone (``mcap_fast.read_topics``).
Each line gives the wall-clock rate of the fastest of the repeats and the
CPU seconds (all threads) of that run: on a machine shared with other work
the wall figures fall, the CPU seconds much less, so the CPU ratio tells
what the code costs against zstd alone.

    python bench/mcap_ingest.py [--rotation-samples 20000] [--repeats 3] [--workers 0] [--cdr-only]
"""

from __future__ import annotations

import argparse
import itertools
import json
import struct
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import zstandard  # noqa: E402
from common import report  # noqa: E402
from mcap.opcode import Opcode  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from rotcal.config import Limits  # noqa: E402
from rotcal.ingest.formats.mcap.fast import read_topics  # noqa: E402
from rotcal.ingest.formats.mcap.reader import read_mcap_capture  # noqa: E402
from rotcal.ingest.formats.mcap.records import McapFile, top_records  # noqa: E402
from rotcal.ingest.meta import load_meta  # noqa: E402
from rotcal.parallel import cores  # noqa: E402
from rotcal.simulate import Plan, SimulationSpec, simulate, write_mcap  # noqa: E402


def reference_cdr(path: Path) -> list:
    t, u, v, w = [], [], [], []
    with path.open("rb") as fh:
        for _, _, _, msg in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/imu"]):
            t.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            u.append(msg.linear_acceleration.x)
            v.append(msg.linear_acceleration.y)
            w.append(msg.linear_acceleration.z)
    return u


def reference_json(path: Path) -> list:
    t, u, v, w = [], [], [], []
    with path.open("rb") as fh:
        for _, _, message in make_reader(fh).iter_messages(topics=["/imu"]):
            m = json.loads(message.data)
            t.append(m["t"])
            u.append(m["u"])
            v.append(m["v"])
            w.append(m["w"])
    return u


def compressed_chunks(path: Path) -> list[tuple[memoryview, int]]:
    """Each chunk's compressed records, read into memory, and the bytes it expands to."""
    payloads = []
    with path.open("rb") as fh:
        for opcode, _, length in top_records(fh, McapFile(path, Limits())):
            if opcode == Opcode.CHUNK:
                body = fh.read(length)
                start = 32 + struct.unpack_from("<I", body, 28)[0] + 8  # past the header and the compression name
                payloads.append((memoryview(body)[start:], struct.unpack_from("<Q", body, 16)[0]))
    return payloads


def decompress_all(pool: ThreadPoolExecutor, payloads: list[tuple[memoryview, int]], out: memoryview) -> None:
    """zstd alone: every chunk into its place in one buffer allocated beforehand."""
    bases = [0, *itertools.accumulate(size for _, size in payloads)]

    def one(k: int) -> int:
        return zstandard.ZstdDecompressor().stream_reader(payloads[k][0]).readinto(out[bases[k] : bases[k + 1]])

    assert sum(pool.map(one, range(len(payloads)))) == bases[-1]


def timed(fn, repeats: int) -> tuple[float, float]:
    """(wall, CPU) seconds of the fastest of ``repeats`` calls, after one warm-up."""
    fn()
    runs = []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        runs.append((time.perf_counter() - wall, time.process_time() - cpu))
    return min(runs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotation-samples", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=0, help="cores the run may use (0: all)")
    parser.add_argument("--cdr-only", action="store_true", help="skip the JSON capture")
    args = parser.parse_args()
    threads = cores(args.workers)
    spec = SimulationSpec(plan=Plan(rotation_samples=args.rotation_samples))
    sim = simulate(spec, 1)
    n = sim.samples.height
    meta = load_meta(None)
    cases = (("cdr", reference_cdr),) if args.cdr_only else (("cdr", reference_cdr), ("json", reference_json))
    with tempfile.TemporaryDirectory() as tmp:
        for encoding, reference in cases:
            path = write_mcap(sim, Path(tmp) / f"{encoding}.mcap", encoding=encoding)
            assert len(reference(path)) == n
            what = f"MCAP {encoding.upper()} ingest ({n:,} Imu messages, {path.stat().st_size / 1e6:.1f} MB, {threads} cores)"
            ours = timed(partial(read_mcap_capture, path, meta, None, Limits(), args.workers), args.repeats)
            theirs = timed(partial(reference, path), args.repeats)
            report(what, n, "messages", ours[0], "make_reader + per-message decode", theirs[0])
            print(f"  CPU s: ingest {ours[1]:.3f}, per-message path {theirs[1]:.3f}: ratio {theirs[1] / ours[1]:.1f}x")
            if encoding == "cdr":
                payloads = compressed_chunks(path)
                with ThreadPoolExecutor(threads) as pool:
                    out = memoryview(bytearray(sum(size for _, size in payloads)))
                    bound = timed(partial(decompress_all, pool, payloads, out), args.repeats)
                columns = timed(partial(read_topics, path, {"/imu"}, Limits(), args.workers), args.repeats)
                report(what, n, "messages", ours[0], "zstd alone (the bound)", bound[0])
                print(f"  CPU s: ingest {ours[1]:.3f}, zstd alone {bound[1]:.3f}: ratio {bound[1] / ours[1]:.2f}")
                report("  decoding into columns alone (read_topics)", n, "messages", columns[0], "zstd alone (the bound)", bound[0])
                print(f"  CPU s: read_topics {columns[1]:.3f}, zstd alone {bound[1]:.3f}: ratio {bound[1] / columns[1]:.2f}")
                print(f"of the bound ({threads} cores; the wall ratios mean something on a quiet machine only): ingest wall "
                      f"{bound[0] / ours[0]:.2f}, CPU {bound[1] / ours[1]:.2f}; read_topics wall {bound[0] / columns[0]:.2f}, "
                      f"CPU {bound[1] / columns[1]:.2f}")


if __name__ == "__main__":
    main()
