"""Valid recordings made degenerate, and the invariant they must keep
(docs/fuzzing.md, "Degenerate recordings"): used by
``tests/test_degenerate_properties.py`` (hypothesis, a short run) and
``scripts/degenerate.py`` (the long run).

A recording is drawn from a generator: a static recording of jig positions
(4 to 16 positions of random or face directions, 50 to 200 samples each)
or a small table plan (three axes, a step sequence and rotations at 0.05
and 0.5 Hz), then one degeneration is applied:

- ``noise_free``: the outputs without noise (integer outputs: identical
  samples in each pose; or floats: exact values);
- ``quantized``: every output rounded to a multiple of 1 to 1000 counts;
- ``dead``, ``stuck``, ``saturated``: a channel all zero, at one value, or
  clipped at a limit that 1 g passes;
- ``alike``: every position within a few degrees of one direction;
- ``exact``: four positions (the 12 parameters exactly determined);
- ``radians``, ``rpm``: the table's angle column in radians, its rate in
  rpm.

The invariant: ``run_dataset`` refuses the recording with a ``RotcalError``
whose message is one line, or publishes a result whose every published
float is finite and whose recommended values lie within ``Z_MAX`` standard
uncertainties of the truth, with no effect found (the truth has none: a
finding is the degeneration's alone). Anything else (another exception, a
finding, a value off its uncertainty) is a violation.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import ReportConfig, RunConfig
from rotcal.errors import RotcalError
from rotcal.model.physics import CHANNELS
from rotcal.run import run_dataset
from rotcal.simulate import DutSpec, Plan, SimulationSpec, simulate, write_dataset

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from posesim import G_LOCAL, HAND_POSES, hand_placed, random_directions  # noqa: E402

STATIC_KINDS = ("noise_free", "quantized", "dead", "stuck", "saturated", "alike", "exact")
TABLE_KINDS = ("noise_free", "quantized", "dead", "stuck", "radians", "rpm")
# |value - truth| / u beyond which a published value is a violation: over thousands of recordings
# of nine parameters each, a larger bound than a single test's 3 keeps chance exceedances away
Z_MAX = 5.0
SMALL_PLAN = Plan(step_deg=45.0, step_samples=12, rates_hz=(0.05, 0.5), rotation_samples=400)


@dataclass(frozen=True)
class Drawn:
    """A degenerate recording: where it is, its kind, what was drawn and
    the truth of its nine parameters."""

    path: Path
    kind: str
    detail: str
    truth: np.ndarray


def _jig_csv(path: Path, t_s: np.ndarray, y: np.ndarray, reference: np.ndarray) -> None:
    path.mkdir(parents=True)
    pl.DataFrame({"t": t_s, **{c: y[:, r] for r, c in enumerate(CHANNELS)},
                  **{c: reference[:, r] for r, c in enumerate(("gx", "gy", "gz"))}}).write_csv(path / "positions.csv")
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n'
                                       "g_local_uncertainty = 0.0\n")


def static_recording(rng: np.random.Generator, kind: str, path: Path, step: float | None = None) -> Drawn:
    """Jig positions of a DUT drawn as ``simulate`` draws one, made ``kind``
    (``step``: the quantization's, else drawn)."""
    seed = int(rng.integers(2**31))
    n_poses = 4 if kind == "exact" else int(rng.integers(6, 17))
    faces = kind not in ("alike", "exact") and rng.random() < 0.3
    directions = (HAND_POSES[:6] if faces else random_directions(rng, n_poses))
    if kind == "alike":
        centre = random_directions(rng, 1)[0]
        directions = centre + rng.normal(0.0, np.deg2rad(rng.uniform(0.1, 3.0)), (n_poses, 3))
        directions /= np.linalg.norm(directions, axis=1)[:, None]
    noise = 0.0 if kind == "noise_free" else float(rng.uniform(0.5, 10.0))
    integer = not (kind == "noise_free" and rng.random() < 0.5)
    sim = hand_placed(seed, samples=int(rng.integers(50, 201)), noise=noise, directions=directions, integer=integer)
    y, detail = sim.y.copy(), f"seed {seed}, {len(directions)} positions, noise {noise:.3g}"
    channel = int(rng.integers(3))
    if kind == "quantized":
        step = float(rng.choice([1, 2, 5, 10, 50, 100, 200, 500, 1000])) if step is None else step
        y = np.round(y / step) * step
        detail += f", step {step:g}"
    elif kind in ("dead", "stuck"):
        y[:, channel] = 0.0 if kind == "dead" else float(rng.integers(-30000, 30000))
        detail += f", channel {CHANNELS[channel]}"
    elif kind == "saturated":
        limit = float(np.abs(sim.y[:, channel]).max() * rng.uniform(0.3, 0.9))
        y[:, channel] = np.clip(y[:, channel], -limit, limit)
        detail += f", channel {CHANNELS[channel]} clipped at +-{limit:.0f}"
    _jig_csv(path, sim.t_ns / 1e9, y, sim.directions[sim.pose])
    return Drawn(path, f"static {kind}", detail, sim.truth)


def table_recording(rng: np.random.Generator, kind: str, path: Path, step: float | None = None) -> Drawn:
    """A small table plan as per-segment CSV files, made ``kind`` (``step``:
    the quantization's, else drawn)."""
    seed = int(rng.integers(2**31))
    spec = SimulationSpec(plan=SMALL_PLAN, dut=DutSpec(noise_std=0.0) if kind == "noise_free" else DutSpec())
    write_dataset(simulate(spec, seed), spec, path, "csv")
    truth = json.loads((path / "truth.json").read_text())["intrinsic"]
    detail, channel = f"seed {seed}", CHANNELS[int(rng.integers(3))]
    drawn_step = float(rng.choice([1, 2, 5, 10, 50, 100, 200, 500, 1000]))
    step = drawn_step if step is None else step
    value = float(rng.integers(-30000, 30000))
    change = {"quantized": {c: (pl.col(c) / step).round() * step for c in CHANNELS},
              "dead": {channel: pl.lit(0.0)}, "stuck": {channel: pl.lit(value)},
              "radians": {"angle_deg": pl.col("angle_deg").radians()},
              "rpm": {"rate_hz": pl.col("rate_hz") * 60}}.get(kind, {})
    detail += {"quantized": f", step {step:g}", "dead": f", channel {channel}", "stuck": f", channel {channel}"}.get(kind, "")
    for csv in sorted(path.glob("*.csv")):
        frame = pl.read_csv(csv)
        frame.with_columns(**{name: expr for name, expr in change.items() if name in frame.columns}).write_csv(csv)
    return Drawn(path, f"table {kind}", detail, np.array([truth[k] for k in _INTRINSIC]))


_INTRINSIC = ("s_u", "s_v", "s_w", "phi_uv", "phi_vw", "phi_wu", "O_u", "O_v", "O_w")


def draw(rng: np.random.Generator, path: Path) -> Drawn:
    """One degenerate recording: static or table (two to one), its kind uniform."""
    if rng.random() < 2 / 3:
        return static_recording(rng, str(rng.choice(STATIC_KINDS)), path)
    return table_recording(rng, str(rng.choice(TABLE_KINDS)), path)


# the run as a batch runs it (figures off; the diagnosis and its report on)
CONFIG = RunConfig(report=ReportConfig(figures=False))


def violation(drawn: Drawn, out: Path) -> str | None:
    """The invariant checked on one recording: None, or what broke it."""
    try:
        run_dataset(drawn.path, out, config=CONFIG)
    except RotcalError as exc:
        return f"a refusal of {len(str(exc).splitlines())} lines: {exc}" if "\n" in str(exc) else None
    except Exception as exc:  # noqa: BLE001  (any other exception is the violation reported)
        return f"{type(exc).__name__}: {exc}"
    return published_violation(drawn.truth, out)


def published_violation(truth: np.ndarray, out: Path) -> str | None:
    """The invariant on a published result in ``out`` (its tables): None,
    or what broke it."""
    intrinsic = pl.read_parquet(out / "intrinsic.parquet").filter(pl.col("recommended"))
    for name in intrinsic.columns:
        if intrinsic[name].dtype == pl.Float64 and not intrinsic[name].drop_nulls().is_finite().all():
            return f"intrinsic.parquet: a non-finite {name}"
    for rate in intrinsic["rate_hz"].unique().to_list():
        rows = intrinsic.filter(pl.col("rate_hz") == rate)
        value, u = rows["value"].to_numpy(), rows["std_uncertainty"].fill_null(np.nan).to_numpy()
        fitted = u > 0  # a model's fixed parameters (orthogonal axes) have u = 0
        z = (value - truth)[fitted] / u[fitted]
        if np.any(~(np.abs(z) < Z_MAX)):
            return f"{rate:g} Hz: {np.array(rows['parameter'])[fitted][np.argmax(np.abs(z))]} {np.abs(z).max():.2f} u off the truth"
    diagnosis = out / "diagnosis.parquet"
    if diagnosis.exists():
        found = pl.read_parquet(diagnosis).filter(pl.col("detected"))
        if found.height:
            return f"findings the truth has not: {', '.join(sorted(set(found['effect'])))}"
    return None
