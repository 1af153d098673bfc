"""MCAP ingest, messages per second: rotcal's ingest of a simulated capture
(``sensor_msgs/msg/Imu`` in CDR, zstd chunks; and JSON messages) against
the reference path a user would write: ``mcap.reader.make_reader`` with the
``mcap_ros2`` decoder (json.loads for JSON), one message at a time into
Python lists. rotcal's figure includes everything ingest does (table channel
mapped onto the samples, validation, canonical columns); the reference only
decodes the DUT topic.

    python bench/mcap_ingest.py [--rotation-samples 20000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import best_of, report  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from rotcal.config import Limits  # noqa: E402
from rotcal.ingest.mcap_source import read_mcap_capture  # noqa: E402
from rotcal.ingest.meta import load_meta  # noqa: E402
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotation-samples", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    spec = SimulationSpec(plan=Plan(rotation_samples=args.rotation_samples))
    sim = simulate(spec, 1)
    n = sim.samples.height
    meta = load_meta(None)
    with tempfile.TemporaryDirectory() as tmp:
        for encoding, reference in (("cdr", reference_cdr), ("json", reference_json)):
            path = write_mcap(sim, Path(tmp) / f"{encoding}.mcap", encoding=encoding)
            assert len(reference(path)) == n
            ours = best_of(partial(read_mcap_capture, path, meta, None, Limits()), args.repeats)
            theirs = best_of(partial(reference, path), args.repeats)
            report(f"MCAP {encoding.upper()} ingest ({n:,} Imu messages, {path.stat().st_size / 1e6:.1f} MB)",
                   n, "messages", ours, "make_reader + per-message decode", theirs)


if __name__ == "__main__":
    main()
