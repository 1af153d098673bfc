"""Coverage: is a reported standard uncertainty honest? Simulate many clean
datasets, reduce each, and test for every parameter (pooled over rates) the
normalised errors z = (estimate - truth) / u in two ways (GUM JCGM 100
sections 6.2 and G.3; JCGM 101 section 8 validates an uncertainty the same
way):

- coverage: how often |z| <= 2. For honest, normal uncertainties the
  fraction is 95.45 %; with n trials the count is binomial, and the check
  passes when it lies in the central 99.9 % binomial interval around it.
  Uncertainties too large never fail it when n is small (all n within 2 u
  is inside the interval), hence
- spread: the mean of z^2, which for honest uncertainties is chi^2(n) / n.
  The check passes when it lies in the central 1 - 1e-5 interval, i.e. when
  the RMS of z is consistent with 1; uncertainties k times too large give an
  RMS near 1/k. With 24 datasets of five rates (120 trials, RMS accepted
  from 0.72 to 1.31) uncertainties 2x too large or too small pass one
  parameter with probability below 1e-7.

The true g of each simulated dataset is drawn from N(g_local, u(g)^2) while
the pipeline is given the nominal g_local (as a site's dataset.toml would):
otherwise the g_local contribution to u would be checked against no error
at all and the sensitivities would look over-covered.
"""

from __future__ import annotations

import multiprocessing
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
import polars as pl
from scipy.stats import binom, chi2

from rotcal.combine.labelled import combine
from rotcal.config import FitConfig
from rotcal.fit.segments import fit_segments, fits_frame
from rotcal.ingest.dataset import Dataset, load_dataset
from rotcal.metrology.uncertainty import COVERAGE_PROBABILITY
from rotcal.model.physics import INTRINSIC
from rotcal.model.results import IntrinsicResult
from rotcal.segment.labelled import segment_by_labels
from rotcal.simulate import SimulationSpec, simulate, write_dataset

CONFIDENCE = 0.999
# per parameter: nine parameters together fail an honest run with p < 1e-4
SPREAD_CONFIDENCE = 1 - 1e-5
# The z of one parameter at two rates of one dataset share the g_local draw
# only: at most 14 % of a sensitivity's variance (default plan), so their
# correlation is at most 0.15 and that of their squares 2 * 0.15^2. This
# widens the variance of the mean of z^2 by at most 1 + (rates - 1) * 0.0225
# (9 % for five rates): the spread test counts n / that effective trials.
RATE_CORRELATION = 0.15


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
    # spawned, as the batch's workers: a fork after polars' thread pool started deadlocks
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return np.array(list(pool.map(_job, jobs, chunksize=4)))


def coverage_frame(z: np.ndarray) -> pl.DataFrame:
    """Per parameter, z pooled over datasets and rates (z: (datasets, rates,
    9)): trials, the fraction within 2 u with its 99.9 % binomial
    acceptance interval around 95.45 %, the RMS of z with its acceptance
    interval from chi^2 (module docstring), and whether each passed."""
    flat = z.reshape(-1, len(INTRINSIC))
    n = flat.shape[0]
    low, high = binom.interval(CONFIDENCE, n, COVERAGE_PROBABILITY)
    within = np.sum(np.abs(flat) <= 2.0, axis=0)
    dof = n / (1 + (z.shape[1] - 1) * RATE_CORRELATION**2)
    rms_low, rms_high = np.sqrt(np.array(chi2.interval(SPREAD_CONFIDENCE, dof)) / dof)
    z_rms = np.sqrt(np.mean(flat**2, axis=0))
    passed_2u = (within >= low) & (within <= high)
    passed_spread = (z_rms >= rms_low) & (z_rms <= rms_high)
    column = partial(np.full, len(INTRINSIC))
    return pl.DataFrame({
        "parameter": list(INTRINSIC),
        "trials": column(n),
        "within_2u": within,
        "fraction": within / n,
        "interval_low": column(low / n),
        "interval_high": column(high / n),
        "z_rms": z_rms,
        "z_rms_low": column(rms_low),
        "z_rms_high": column(rms_high),
        "max_abs_z": np.abs(flat).max(axis=0),
        "passed_2u": passed_2u,
        "passed_spread": passed_spread,
        "passed": passed_2u & passed_spread,
    })
