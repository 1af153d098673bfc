"""Channels a static recording cannot calibrate, recognised from its poses:
a channel that reads one value in every pose (dead, stuck or disconnected:
no sensitivity to find), or poses pinned without scatter at its extremes
where the other poses' linear model puts them beyond (or, where the others
do not determine it, while every other pose scatters): saturated at the
converter's limit. Either makes a fit claim a
sensitivity or an offset the channel never showed; the reduction is
refused with the reason. (The table path refuses the same fault per
segment: ``fit.refusals.stuck_from``.)"""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS

# poses pinned at one extreme beyond which a channel counts as saturated: one pose alone may sit
# at the extreme with identical samples (quiet or coarsely quantized outputs)
MIN_PINNED_POSES = 2
# how much quieter than the others poses pinned at an extreme must be when nothing else tells a limit
CLEARLY_QUIETER = 4.0


def channel_fault(positions: pl.DataFrame) -> str | None:
    """Why the pose table's channels cannot be calibrated, or None: the
    first dead or stuck channel, else the first saturated one."""
    means = positions.select(f"mean_{c}" for c in CHANNELS).to_numpy()
    var = np.array(positions["cov_mean"].to_list(), float).reshape(-1, 3, 3)[:, [0, 1, 2], [0, 1, 2]] \
        if positions.height else np.zeros((0, 3))
    if len(means) < 2:
        return None
    for r, channel in enumerate(CHANNELS):
        if np.all(means[:, r] == means[0, r]):
            return (f"channel {channel} reads {means[0, r]:g} in every one of the {len(means)} poses (dead, stuck or "
                    "disconnected): it shows no sensitivity to calibrate, so no result is given")
    if "ref_x" not in positions.columns:
        return None  # dwells of unknown orientation
    reference = positions.select("ref_x", "ref_y", "ref_z").to_numpy()
    if not np.isfinite(reference).all():
        return None  # without references a pinned pose cannot be told from a quiet one
    design = np.column_stack([reference, np.ones(len(means))])
    for r, channel in enumerate(CHANNELS):
        # at an extreme, with no more scatter than the quietest pose (identical samples)
        quiet = var[:, r] <= 1.01 * var[:, r].min()
        upper, lower = (means[:, r] == means[:, r].max()) & quiet, (means[:, r] == means[:, r].min()) & quiet
        pinned = upper | lower
        if np.count_nonzero(pinned) < MIN_PINNED_POSES or not _saturated(design, means[:, r], var[:, r], upper, lower):
            continue
        held = sorted({f"{v:g}" for v in means[pinned, r]})
        return (f"channel {channel} reads {' or '.join(held)} without scatter in {np.count_nonzero(pinned)} of the "
                f"{len(means)} poses, where gravity's projection differs between them (saturated at its limit); "
                "poses within its range, or a range setting that holds 1 g, would calibrate it")
    return None


def _saturated(design: np.ndarray, means: np.ndarray, var: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> bool:
    """Whether poses pinned at the channel's extremes are a limit's, not a
    coarse output step's. Where the other poses determine the channel's
    linear model, saturated poses lie beyond the value they hold by more
    than the model's spread; where they do not, the pinned poses must be
    clearly quieter than every other: a coarse step quiets them all, and
    poses of one noise differ in variance by chance (six faces of 200
    samples: about 10 %), so a factor of 4 is asked."""
    pinned = upper | lower
    free = ~pinned
    if np.linalg.matrix_rank(design[free]) < 4:
        return bool(free.any() and var[pinned].max() < var[free].min() / CLEARLY_QUIETER)
    coef, *_ = np.linalg.lstsq(design[free], means[free], rcond=None)
    spread = np.sqrt(np.mean((design[free] @ coef - means[free]) ** 2))
    sign = np.where(upper, 1.0, -1.0)[pinned]
    beyond = sign * (design[pinned] @ coef - means[pinned])
    return bool(np.all(beyond > 3 * spread + np.sqrt(var.max())))
