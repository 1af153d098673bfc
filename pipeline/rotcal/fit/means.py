"""Pose means: each still interval's mean output and the covariance of
that mean, the fit of a constant to a still segment (GUM 4.2.3: the
experimental standard deviation of the mean), widened where the noise is
correlated from sample to sample (``fit.correlated``). The segmentation's
dwells and the static reductions' poses both summarise their samples here."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.fit.correlated import density_ratio, grouped_autocorrelation
from rotcal.fit.quantization import mean_rounding_variance, output_step
from rotcal.model.physics import CHANNELS


def group_statistics(y: np.ndarray, group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group: sample count, mean (G, 3) and covariance of the mean
    (G, 3, 3) of the rows of ``y`` labelled ``group`` (0 .. G-1; -1 = none).

    Where a group's samples are correlated from one to the next (lag-1
    autocorrelation significant and positive), the covariance is widened
    by the noise density's ratio to white at zero frequency
    (``fit.correlated``). A quantized output (its step found from the
    samples) adds the rounding's variance of a mean to the diagonal
    (``fit.quantization``): a pose of identical samples is uncertain by
    the step, not by the step over the square root of its count.
    """
    inside = group >= 0
    first, last = (int(np.argmax(inside)), inside.size - int(np.argmax(inside[::-1]))) if inside.any() else (0, 0)
    if inside.any() and inside[first:last].all():  # the groups one run of rows (a single pose): views, no copy
        g, yy = group[first:last], y[first:last]
    else:
        g, yy = group[inside], y[inside]
    counts = np.bincount(g, minlength=n_groups).astype(float)
    means = np.column_stack([np.bincount(g, weights=yy[:, r], minlength=n_groups) for r in range(3)]) / counts[:, None]
    centred = np.empty(yy.shape)
    for r in range(3):  # a column at a time: no (n, 3) temporary of the means
        np.subtract(yy[:, r], means[g, r], out=centred[:, r])
    scatter = np.stack([np.bincount(g, weights=centred[:, i] * centred[:, j], minlength=n_groups)
                        for i in range(3) for j in range(3)], axis=1).reshape(n_groups, 3, 3)
    with np.errstate(divide="ignore", invalid="ignore"):  # a one-sample group: NaN, refused by reduce_static
        cov = scatter / ((counts - 1.0) * counts)[:, None, None]
    # noise correlated from sample to sample: a mean's variance is the noise density at zero frequency
    widen = np.sqrt(density_ratio(*grouped_autocorrelation(centred, g, n_groups, g), counts[:, None], 0.0))
    cov = cov * widen[:, :, None] * widen[:, None, :]
    if yy.size:
        # the output step's rounding, the same for every sample of a pose when the noise is below it
        # (each pose's own scatter: a pose dithering across a level boundary says nothing of the others)
        with np.errstate(divide="ignore", invalid="ignore"):
            sample_var = np.einsum("kii->ki", scatter) / (counts - 1.0)[:, None]
        diag = np.einsum("kii->ki", cov)
        diag += mean_rounding_variance(output_step(yy)[None], sample_var)
    return counts.astype(np.int64), means, cov


def pose_table(t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> pl.DataFrame:
    """Mean and covariance of the mean of each pose (samples ``starts[k]:stops[k]``)."""
    starts, stops = np.asarray(starts, np.int64), np.asarray(stops, np.int64)
    group = np.full(t_ns.size, -1, np.int64)
    for k, (a, b) in enumerate(zip(starts, stops)):  # poses do not overlap; a few hundred slices, no n-long temporaries
        group[a:b] = k
    counts, means, cov = group_statistics(y, group, starts.size)
    return pl.DataFrame({
        "pose": np.arange(starts.size, dtype=np.int64), "t_start_ns": t_ns[starts], "t_end_ns": t_ns[stops - 1],
        "n_samples": counts, **{f"mean_{c}": means[:, r] for r, c in enumerate(CHANNELS)},
        "cov_mean": cov.reshape(-1, 9).tolist(),
    }, schema_overrides={"cov_mean": pl.List(pl.Float64)})
