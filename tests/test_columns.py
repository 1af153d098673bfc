"""A capture's outputs read as the sample table's columns (``rotcal.model.columns``)
and the sums worked a block at a time give what the whole (n, 3) array
gives, bit for bit: the pose statistics, the stillness detector's
intervals and rejections, the means of rows in either memory layout."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

import rotcal.fit.means as means_module
import rotcal.model.columns as columns_module
import rotcal.segment.stillness as stillness_module
from rotcal.fit.correlated import density_ratio, grouped_autocorrelation
from rotcal.fit.means import group_statistics
from rotcal.fit.quantization import mean_rounding_variance, output_step
from rotcal.model.columns import Outputs
from rotcal.segment.stillness import StillnessConfig, _covered, still_and_short

from handsim import hand_session


def _whole_array_statistics(y: np.ndarray, group: np.ndarray, n_groups: int):
    """``group_statistics`` as the plain expressions on the whole (n, 3) array."""
    inside = group >= 0
    g, yy = group[inside], y[inside]
    counts = np.bincount(g, minlength=n_groups).astype(float)
    means = np.column_stack([np.bincount(g, weights=yy[:, r], minlength=n_groups) for r in range(3)]) / counts[:, None]
    centred = yy - means[g]
    scatter = np.stack([np.bincount(g, weights=centred[:, i] * centred[:, j], minlength=n_groups)
                        for i in range(3) for j in range(3)], axis=1).reshape(n_groups, 3, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = scatter / ((counts - 1.0) * counts)[:, None, None]
    widen = np.sqrt(density_ratio(*grouped_autocorrelation(centred, g, n_groups, g), counts[:, None], 0.0))
    cov = cov * widen[:, :, None] * widen[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        sample_var = np.einsum("kii->ki", scatter) / (counts - 1.0)[:, None]
    diag = np.einsum("kii->ki", cov)
    diag += mean_rounding_variance(output_step(yy)[None], sample_var)
    return counts.astype(np.int64), means, cov


def _poses(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Six poses of correlated, integer noise (1,000 to 3,000 samples) with moves (-1) between them."""
    rng = np.random.default_rng(seed)
    blocks, group = [], []
    for k in range(6):
        n = int(rng.integers(1000, 3000))
        noise = np.cumsum(rng.normal(0.0, 3.0, (n, 3)), axis=0) * 0.05 + rng.normal(0.0, 4.0, (n, 3))
        blocks += [np.round(rng.normal(0.0, 16000.0, 3) + noise), rng.normal(0.0, 8000.0, (int(rng.integers(1, 50)), 3))]
        group += [np.full(n, k), np.full(len(blocks[-1]), -1)]
    return np.concatenate(blocks), np.concatenate(group)


@pytest.mark.parametrize("block", [5, 64, 1 << 18])
def test_pose_statistics_block_by_block_are_the_whole_arrays(monkeypatch, block):
    """Counts, means and covariances of the means (with their widening for
    correlated noise and the rounding's variance) of six poses, from the
    (n, 3) array or its columns, in blocks of 5, 64 and 2^18 samples: those
    of the whole-array expressions, bit for bit."""
    monkeypatch.setattr(means_module, "SUM_BLOCK", block)
    y, group = _poses(3)
    expected = _whole_array_statistics(y, group, 6)
    frame = pl.DataFrame({c: y[:, r] for r, c in enumerate("uvw")})
    for given in (y, Outputs.of_frame(frame), Outputs.of_frame(frame, fortran=True)):
        for got, want in zip(group_statistics(given, group, 6), expected):
            np.testing.assert_array_equal(got, want)


def test_rows_and_means_of_columns_are_the_arrays(monkeypatch):
    """Rows gathered from columns are the (n, 3) array's in its layout
    (``np.column_stack``: C; polars' ``to_numpy``: Fortran), and a mean over
    rows sums in that layout's order, also across blocks of 1,000."""
    monkeypatch.setattr(columns_module, "BLOCK", 1000)
    rng = np.random.default_rng(5)
    frame = pl.DataFrame({c: rng.normal(7.0, 1e3, 12345) for c in "uvw"})
    for fortran, whole in ((False, np.column_stack([frame[c].to_numpy() for c in "uvw"])),
                           (True, frame.select("u", "v", "w").to_numpy())):
        outputs = Outputs.of_frame(frame, fortran=fortran)
        assert whole.flags.f_contiguous == fortran
        for a, b in ((0, 12345), (17, 4321), (999, 1001), (5000, 5001)):
            np.testing.assert_array_equal(outputs.mean(a, b), whole[a:b].mean(axis=0))
            rows = outputs.rows(slice(a, b))
            np.testing.assert_array_equal(rows, whole[a:b])
            assert rows.flags.f_contiguous == fortran or b - a == 1


def test_still_intervals_from_columns_are_those_of_the_array(monkeypatch):
    """A hand session with two shaken rests, one cut short and one split by
    a jump: the still intervals and the rejections (too noisy, too short)
    from the columns, in either layout and in blocks of 300 samples, are
    the array's."""
    frame, _ = hand_session(3, n_poses=12)
    rng = np.random.default_rng(3)
    shaken = np.zeros(frame.height)
    shaken[5 * 700 : 5 * 700 + 400] = shaken[9 * 700 : 9 * 700 + 400] = 1.0
    jump = np.zeros(frame.height)
    jump[7 * 700 + 200 : 7 * 700 + 400] = 300.0  # the eighth rest's output jumps between two samples: two rests
    frame = frame.with_columns(**{c: pl.col(c) + jump + np.round(shaken * rng.normal(0.0, 31.0, frame.height)) for c in "uvw"})
    t_ns = np.round(frame["t"].to_numpy() * 1e9).astype(np.int64)
    t_ns[2 * 700 + 150 :] += 2_000_000_000  # a time gap cuts the third rest: 1.5 s, short of the 2 s asked
    config = StillnessConfig(min_dwell_s=2.0)
    still, rejected = still_and_short(t_ns, np.column_stack([frame[c].to_numpy() for c in "uvw"]), config)
    assert rejected["reason"].str.starts_with("too noisy").sum() == 2 and rejected["reason"].str.starts_with("shorter").any()
    assert np.any(still["stop"].to_numpy() == 7 * 700 + 200) and np.any(still["start"].to_numpy() == 7 * 700 + 200)
    monkeypatch.setattr(stillness_module, "VARIANCE_BLOCK", 300)
    for fortran in (False, True):
        got = still_and_short(t_ns, Outputs.of_frame(frame, fortran=fortran), config)
        assert got[0].equals(still) and got[1].equals(rejected)


def test_quiet_windows_cover_their_samples():
    """Every sample inside a quiet window, as counting each window's start
    and end gives it, for runs far closer together than a window (hundreds
    of them overlapping)."""
    rng = np.random.default_rng(1)
    for window, p in ((3, 0.5), (700, 0.5), (700, 0.02), (50, 0.98), (50, 0.0)):
        quiet = rng.random(20000 - window + 1) < p
        quiet[:5] = rng.random() < p
        cover = np.zeros(20001, int)
        np.add.at(cover, np.flatnonzero(quiet), 1)
        np.add.at(cover, np.flatnonzero(quiet) + window, -1)
        np.testing.assert_array_equal(_covered(quiet, window, 20000), np.cumsum(cover[:-1]) > 0)
