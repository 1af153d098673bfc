"""Coverage: is a reported standard uncertainty honest? Simulate many clean
datasets, reduce each, and count for every parameter (pooled over rates)
how often |estimate - truth| <= 2 u. For honest, normal uncertainties the
fraction is 95.45 %; with n trials the count is binomial, and the check
passes when it lies in the central 99.9 % binomial interval around it.

The true g of each simulated dataset is drawn from N(g_local, u(g)^2) while
the pipeline is given the nominal g_local (as a site's dataset.toml would):
otherwise the g_local contribution to u would be checked against no error
at all and the sensitivities would look over-covered.
"""

from __future__ import annotations

import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import polars as pl
from scipy.stats import binom

from rotcal.combine.labelled import combine
from rotcal.config import FitConfig
from rotcal.fit.segments import fit_segments, fits_frame
from rotcal.ingest import Dataset, load_dataset
from rotcal.metrology.uncertainty import COVERAGE_PROBABILITY
from rotcal.model.physics import INTRINSIC
from rotcal.model.results import IntrinsicResult
from rotcal.segment.labelled import segment_by_labels
from rotcal.simulate.core import SimulationSpec, simulate, write_dataset

CONFIDENCE = 0.999


@dataclass(frozen=True, eq=False)
class Reduced:
    """A dataset taken through ingest, segment, fit and combine, in memory."""

    data: Dataset
    samples: pl.DataFrame
    fits: pl.DataFrame
    results: list[IntrinsicResult]


def reduce_dataset(path: Path, fit: FitConfig = FitConfig()) -> Reduced:
    """The first stages of ``run.run_dataset`` without writing anything (one worker)."""
    data = load_dataset(path)
    samples, segments = segment_by_labels(data.samples, data.name, data.meta.angle_source)
    fits = fits_frame(fit_segments(samples, segments, fit, workers=1), segments, data.name)
    results = [r for r in combine(fits, data.meta.g_local, data.meta.g_local_uncertainty) if isinstance(r, IntrinsicResult)]
    return Reduced(data, samples, fits, results)


def normalised_errors(seed: int, spec: SimulationSpec = SimulationSpec(), fit: FitConfig = FitConfig()) -> np.ndarray:
    """(estimate - truth) / u of the nine parameters at every rate of one
    simulated dataset: an array (rates, 9), rates in the pipeline's order."""
    rng = np.random.default_rng([seed, 0x67])
    true_spec = replace(spec, g_local=spec.g_local + spec.g_local_uncertainty * rng.standard_normal())
    sim = simulate(true_spec, seed)
    with tempfile.TemporaryDirectory(prefix="rotcal-coverage-") as tmp:
        reduced = reduce_dataset(write_dataset(sim, spec, Path(tmp) / f"cov{seed}"), fit)
    results = reduced.results
    truth = np.array([sim.truth["intrinsic"][p] for p in INTRINSIC])
    return np.array([(r.value - truth) / r.std_uncertainty for r in results])


def _job(args: tuple) -> np.ndarray:
    return normalised_errors(*args)


def simulate_errors(n: int, first_seed: int = 0, spec: SimulationSpec = SimulationSpec(), fit: FitConfig = FitConfig(),
                    workers: int = 1) -> np.ndarray:
    """Normalised errors of ``n`` seeded datasets: (n, rates, 9)."""
    jobs = [(first_seed + k, spec, fit) for k in range(n)]
    if workers <= 1:
        return np.array([_job(j) for j in jobs])
    with ProcessPoolExecutor(workers) as pool:
        return np.array(list(pool.map(_job, jobs, chunksize=4)))


def coverage_frame(z: np.ndarray) -> pl.DataFrame:
    """Per parameter, pooled over datasets and rates: trials, the fraction
    within 2 u, the 99.9 % binomial acceptance interval around 95.45 % and
    whether the fraction lies in it; with the RMS of z beside it."""
    flat = z.reshape(-1, len(INTRINSIC))
    n = flat.shape[0]
    low, high = binom.interval(CONFIDENCE, n, COVERAGE_PROBABILITY)
    within = np.sum(np.abs(flat) <= 2.0, axis=0)
    return pl.DataFrame({
        "parameter": list(INTRINSIC),
        "trials": np.full(len(INTRINSIC), n),
        "within_2u": within,
        "fraction": within / n,
        "interval_low": np.full(len(INTRINSIC), low / n),
        "interval_high": np.full(len(INTRINSIC), high / n),
        "passed": (within >= low) & (within <= high),
        "z_rms": np.sqrt(np.mean(flat**2, axis=0)),
        "max_abs_z": np.abs(flat).max(axis=0),
    })
