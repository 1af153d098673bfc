"""Reference directions checked against the measured ones before a
reference fit: each position's reference (a pose label, a jig's
``gx, gy, gz``) against the direction its outputs show under the linear
model fitted to the other positions (leave one out). A label of another
pose, or references in another frame or order, would otherwise be fitted:
the 12 parameters bend to it and its excess scatter is published as
uncertainty."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS

# a position whose outputs point further than this from its reference is mislabelled (a jig or a hand
# places within a few degrees)
MAX_ANGLE_DEG = 20.0
# the fewest positions, and the largest condition number of the other positions' design, for the check
MIN_POSITIONS = 6
MAX_CONDITION = 1e3


def reference_fault(positions: pl.DataFrame) -> str | None:
    """Why the positions' references disagree with their outputs, or None:
    the first position whose outputs, through the linear model of the
    others (R = O + C ref, least squares), point more than
    ``MAX_ANGLE_DEG`` from its reference."""
    if positions.height < MIN_POSITIONS:
        return None
    reference = positions.select("ref_x", "ref_y", "ref_z").to_numpy()
    means = positions.select(f"mean_{c}" for c in CHANNELS).to_numpy()
    design = np.column_stack([reference, np.ones(len(means))])
    if not np.isfinite(design).all() or not np.isfinite(means).all():
        return None
    angles, seen = np.zeros(len(means)), np.zeros_like(means)
    for k in range(len(means)):
        others = np.arange(len(means)) != k
        if np.linalg.cond(design[others]) > MAX_CONDITION:
            continue
        coef, *_ = np.linalg.lstsq(design[others], means[others], rcond=None)
        gain, offset = coef[:3].T, coef[3]
        if np.linalg.cond(gain) > MAX_CONDITION:
            continue
        seen[k] = np.linalg.solve(gain, means[k] - offset)
        cosine = seen[k] @ reference[k] / (np.linalg.norm(seen[k]) * np.linalg.norm(reference[k]))
        angles[k] = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    k = int(np.argmax(angles))  # the worst: a wrong reference also bends the others' models a little
    if angles[k] <= MAX_ANGLE_DEG:
        return None
    label = positions["label"][k] if "label" in positions.columns else None
    named = f"position {k + 1}" + (f" ({label})" if label else "")
    shown = ", ".join(f"{v:.2f}" for v in seen[k] / np.linalg.norm(seen[k]))
    return (f"{named}: its outputs point {angles[k]:.0f} degrees from its reference "
            f"({', '.join(f'{v:.3g}' for v in reference[k])}) under the model of the other positions (measured direction "
            f"{shown}; {np.count_nonzero(angles > MAX_ANGLE_DEG)} positions beyond {MAX_ANGLE_DEG:g} degrees): a label or "
            "jig reference of another position, or references in another frame?")
