"""The noise model of the real recordings in ../shared/data/real (their
still parts: imu_tk's initial rest, imucal's six labelled static poses,
each piece's mean removed) with the Allan-deviation figures for
docs/noise.md, and the white density in ug/sqrt(Hz) beside the sensor's
datasheet figure.

    python scripts/noise_real.py --data ../shared/data/real --figures docs
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.noise import NoiseModel
from rotcal.noise.model import identify_channel
from rotcal.report.noise_figure import allan_png

G0 = 9.80665


def _model(pieces: list[np.ndarray], fs_hz: float) -> NoiseModel:
    return NoiseModel(tuple(identify_channel(c, [p[:, r] - p[:, r].mean() for p in pieces], fs_hz, "count")
                            for r, c in enumerate("xyz")), 1 / fs_hz, "count")


def recordings(data: Path) -> dict[str, tuple[list[np.ndarray], float, tuple[float, float, float]]]:
    """name -> (still pieces (n, 3) in counts, sample rate, counts per m/s^2 of x, y, z)."""
    xsens = np.loadtxt(data / "imu_tk_xsens" / "xsens_acc.txt")
    rest = xsens[xsens[:, 0] < xsens[0, 0] + 45.0, 1:]  # imu_tk's initial static interval is 50 s
    session = pl.read_csv(data / "imucal_session" / "annotated_session.csv")
    poses = [session.filter(part=p).select("acc_x", "acc_y", "acc_z").to_numpy().astype(float)
             for p in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")]
    return {"imu_tk_xsens": ([rest], 100.0, (415.0, 413.0, 415.0)),
            "imucal_session": (poses, 204.8, (208.55, 208.00, 214.78))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/real"))
    parser.add_argument("--figures", type=Path, default=None)
    args = parser.parse_args()
    for name, (pieces, fs, scale) in recordings(args.data).items():
        model = _model(pieces, fs)
        print(f"{name}: {len(pieces)} piece(s), {sum(p.shape[0] for p in pieces)} samples at {fs} Hz")
        for ch, s in zip(model.channels, scale):
            ug = 1e6 / (s * G0)
            terms = {t.term + (str(t.index) if t.term.startswith("gauss") else ""): t for t in ch.terms}
            n = terms["white_density"]
            shown = ", ".join(f"{k} {t.value:.3g} +- {t.u:.2g} {t.unit}" for k, t in terms.items()
                              if k != "white_density" and t.value > 2 * t.u)
            print(f"  {ch.channel}: N {n.value * ug:.0f} +- {n.u * ug:.0f} ug/sqrt(Hz); Allan deviation minimum "
                  f"{ch.allan.adev.min() * ug:.0f} ug at {ch.allan.tau_s[np.argmin(ch.allan.adev)]:.2f} s; "
                  f"chi2_reduced {ch.chi2_reduced:.2f}; {shown or 'no other term shown'}")
        if args.figures:
            allan_png(model, args.figures / f"noise_{name}.png", f"{name}: Allan deviation of the still parts (counts)")


if __name__ == "__main__":
    main()
