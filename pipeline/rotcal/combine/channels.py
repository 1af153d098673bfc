"""Channels a static recording cannot calibrate, recognised from its poses:
a channel that reads one value in every pose (dead, stuck or disconnected:
no sensitivity to find), or one value throughout several poses at its
extreme where the other poses' linear model puts them beyond it
(saturated: pinned at the converter's limit). Either makes a fit claim a
sensitivity or an offset the channel never showed; the reduction is
refused with the reason. (The table path refuses the same fault per
segment: ``fit.segments.stuck_from``.)"""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS

# poses pinned at one extreme beyond which a channel counts as saturated: one pose alone may sit
# at the extreme with identical samples (quiet or coarsely quantized outputs)
MIN_PINNED_POSES = 2


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
    reference = positions.select("ref_x", "ref_y", "ref_z").to_numpy()
    if not np.isfinite(reference).all():
        return None  # without references a pinned pose cannot be told from a quiet one
    design = np.column_stack([reference, np.ones(len(means))])
    for r, channel in enumerate(CHANNELS):
        for sign, side in ((1.0, "upper"), (-1.0, "lower")):
            extreme = (sign * means[:, r]).max()
            # at the extreme, with no more scatter than the quietest pose (identical samples)
            pinned = (sign * means[:, r] == extreme) & (var[:, r] <= 1.01 * var[:, r].min())
            free = ~pinned
            if np.count_nonzero(pinned) < MIN_PINNED_POSES or np.linalg.matrix_rank(design[free]) < 4:
                continue
            # saturated: the other poses' linear model puts the pinned ones beyond the value they hold
            # (by more than the poses' spread about that model); a coarse output step does not
            coef, *_ = np.linalg.lstsq(design[free], means[free, r], rcond=None)
            spread = np.sqrt(np.mean((design[free] @ coef - means[free, r]) ** 2))
            beyond = sign * (design[pinned] @ coef) - extreme
            if np.all(beyond > 3 * spread + np.sqrt(var[:, r].max())):
                return (f"channel {channel} reads {sign * extreme:g} without scatter in {np.count_nonzero(pinned)} of "
                        f"the {len(means)} poses where the others put it beyond that (saturated at its {side} limit); "
                        "poses within its range, or a range setting that holds 1 g, would calibrate it")
    return None
