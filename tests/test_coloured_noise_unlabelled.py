"""A default-plan recording of t, u, v, w only (one file, no ``[plan]``
rates): its rotations, found and fitted against their own phase
(``rotcal.segment.unlabelled``), join the segments fitted against the table
angle in the noise's spectrum and the offsets' wander (``fit_segments``'s
``own_phase``), so the phase-free reduction's uncertainties carry coloured
noise as the labelled reduction's do (docs/measured.md, "Coloured noise")."""

import numpy as np
import polars as pl
import pytest

from rotcal.config import RunConfig, RunSection
from rotcal.fit.wander import scatter_wander
from rotcal.ingest.dataset import load_dataset
from rotcal.model.physics import INTRINSIC
from rotcal.run.stages import determined, reduce, segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset

OFFSETS = [INTRINSIC.index(p) for p in INTRINSIC if p.startswith("O")]


def unlabelled(noise: str, seed: int, where) -> tuple[np.ndarray, object, list]:
    """The truth, the segmented recording and the results of one unlabelled default-plan dataset."""
    spec = SimulationSpec().with_noise(noise) if noise else SimulationSpec()
    sim = simulate(spec, seed)
    path = write_dataset(sim, spec, where / f"d{seed}", "csv-unlabelled")
    toml = path / "dataset.toml"
    toml.write_text(toml.read_text().split("\n[plan]")[0])  # the rates from the signals alone
    ds = load_dataset(path)
    seg = segment_and_fit(ds, RunConfig(run=RunSection(workers=1)))
    results, _, _ = determined(reduce(seg, ds), seg, path)
    return np.array([sim.truth["intrinsic"][p] for p in INTRINSIC]), seg, list(results)


@pytest.mark.parametrize("seed", [3, 4])
def test_own_phase_offsets_carry_the_wander(tmp_path, seed):
    """8 counts white and a Gauss-Markov wander of 3 counts, 300 s: every
    own-phase rotation fit carries an offset floor, and the offsets'
    normalised errors at the four rotation rates have an rms below 1.7
    (0.5 and 1.1; 15 to 25 with the own-phase fits' lag widening alone)."""
    truth, seg, results = unlabelled("white_sd=8,gauss_markov=300:3", seed, tmp_path)
    own = seg.fits.filter(pl.col("segment").is_in(list(seg.own_phase)))
    assert own.height == 36 and (own["offset_floor"] > 0).all(), own["offset_floor"]
    z = np.array([(r.value - truth) / r.std_uncertainty for r in results if r.rate_hz != 0])[:, OFFSETS]
    assert z.shape == (4, 3)
    assert np.sqrt(np.mean(z**2)) < 1.7, z


def test_white_noise_leaves_own_phase_fits_as_they_were(tmp_path):
    """White noise: no own-phase fit carries a density ratio or an offset floor."""
    _, seg, _ = unlabelled("", 5, tmp_path)
    own = seg.fits.filter(pl.col("segment").is_in(list(seg.own_phase)))
    assert own.height == 36
    assert (own["noise_ratio_zero"] == 1.0).all() and (own["noise_ratio_rate"] == 1.0).all()
    assert (own["offset_floor"] == 0.0).all()


def test_a_random_walk_is_counted_from_the_record_start():
    """The offsets of twelve segments whose first starts 875 s into the
    record (an unlabelled recording's dwells come first) under a random walk
    of K = 0.05 counts / sqrt(s) from the record's start: the wander the
    first segment carries is at least the walk's variance at its mid-time,
    K^2 1000 s = 2.5 counts^2 (the walk counted from the first segment's
    start gave it 0.30 to 0.37 on this seed)."""
    rng = np.random.default_rng(2)
    t = 1000.0 + 250.0 * np.arange(12)
    c = 100.0 + np.cumsum(rng.standard_normal((12, 3)) * np.sqrt(np.diff(np.r_[0.0, t]))[:, None], axis=0) * 0.05
    c += rng.standard_normal((12, 3)) * 0.01
    wander = scatter_wander(c, [np.eye(12) * 1e-4] * 3, t, np.full(12, 250.0), [("rotation", 0.1)] * 12, ["x"] * 12,
                            record_start_s=0.0)
    assert wander is not None
    s2, corr = wander.s2, wander.correlation(t)
    assert np.all(s2 * corr[0, 0] >= 0.05**2 * 1000.0), s2 * corr[0, 0]


def test_the_dwells_offsets_share_the_segments_wander(tmp_path):
    """A random walk of K = 0.05 counts / sqrt(s) from the record's start.
    The dwells' three groups of 24 (one per table axis, at about 0-95 s,
    1130-1225 s and 2255-2350 s) are 3 s each: too short to see the walk,
    which the rotations' offsets show. Their common offset is the walk's
    mean over the dwells: for three groups of equal weight at t1 < t2 < t3
    its variance is K^2 (5 t1 + 3 t2 + t3) / 9, about 1.7 counts^2 (sd 1.3).
    Without the segments' wander the static result gave u(O) 0.23 counts
    and z of -11.5, 3.9 and 5.4 on seed 0."""
    truth, seg, results = unlabelled("white_sd=8,random_walk_k=0.05", 0, tmp_path)
    static = next(r for r in results if r.rate_hz == 0)
    t = (seg.dwells["t_start_ns"].to_numpy() + seg.dwells["t_end_ns"].to_numpy()) / 2e9
    t -= seg.samples["t_ns"][0] / 1e9
    t1, t2, t3 = (float(np.mean(part)) for part in np.array_split(np.sort(t), 3))
    walk_sd = np.sqrt(0.05**2 * (5 * t1 + 3 * t2 + t3) / 9)
    assert 1.1 < walk_sd < 1.5
    u = static.std_uncertainty[OFFSETS]
    # the wander's size is estimated (its upper bound where slower than the record): u at least the walk's share
    assert np.all(u > 0.8 * walk_sd) and np.all(u < 4 * walk_sd), (u, walk_sd)
    z = (static.value - truth)[OFFSETS] / u
    assert np.all(np.abs(z) < 2.5), z
