"""A long single-pose recording for memory measurements (docs/measured.md,
"Degenerate recordings"): one CSV of ``--samples`` rows at 1 kHz, columns
``t, u, v, w`` (t in seconds, integer counts, no labels), the sensor still
with gravity along w; seeded, so the same arguments write the same bytes.

    python scripts/single_pose_csv.py ds --samples 10000000 --seed 34
    /usr/bin/time -v rotcal run ds --out out
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import polars as pl

# counts: a 16-bit part's offsets and 1 g along w, a few counts of white noise
OFFSET = np.array([37.0, -52.0, 16384.0 + 95.0])
NOISE = 4.0


def write(path: Path, samples: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    path.mkdir(parents=True, exist_ok=True)
    columns = {c: np.round(OFFSET[r] + rng.normal(0.0, NOISE, samples)).astype(np.int32) for r, c in enumerate("uvw")}
    pl.DataFrame({"t": np.arange(samples) / 1000.0, **columns}).write_csv(path / "capture.csv")
    (path / "dataset.toml").write_text('[device]\noutput_unit = "count"\n')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", type=Path)
    parser.add_argument("--samples", type=int, default=10_000_000)
    parser.add_argument("--seed", type=int, default=34)
    args = parser.parse_args()
    write(args.path, args.samples, args.seed)


if __name__ == "__main__":
    main()
