"""Hand placement: what labels and a datasheet say about static poses.

A label (``x_p`` ... ``z_a``) names the face a DUT rested on; a hand never
places a face exactly, so rotcal takes labels as approximate directions.
The poses are fitted without them (``multiposition.orientation_free``: every
pose has |a| = g whatever its tilt), and each pose's corrected direction, in
the sensor's axes, is then compared with its label's: a pose farther from
its label than ``tolerance_deg`` is named with its tilt (``model.placement``
holds what the user states: the tolerance and the datasheet's bound). No
common rotation is taken out: a sensor sits in its case within about a
degree, while a rotation fitted to the other faces would carry their
tilts (up to 3 degrees by hand) into every pose's.

The six faces determine offsets and sensitivities (the orthogonal model,
exactly, six poses for six parameters) but not the three angles between the
axes: a face's cross-axis readings are its tilt plus the axes'
non-orthogonality, and six faces cannot tell them apart. The orthogonal
model fixes the angles at 90 degrees; the datasheet's cross-axis sensitivity
bounds how far they may be from it. rotcal takes that bound as a rectangular
distribution of cos(phi) (GUM 4.3.7: u = bound / sqrt(3)) and carries it into
the offsets and sensitivities as a Type B input (GUM 4.3), through each
pose's tilt (``multiposition.orientation_free``'s ``misalignment_u``), where
the poses do not determine the nine parameters.
"""

from __future__ import annotations

import numpy as np


def label_tilts(directions: np.ndarray, references: np.ndarray) -> np.ndarray:
    """Each pose's angle (degrees) between its corrected direction
    (``directions``, (n, 3), any length, in the sensor's axes) and its
    label's (``references``, unit)."""
    unit = directions / np.linalg.norm(directions, axis=1)[:, None]
    return np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", unit, references), -1.0, 1.0)))


def off_label(tilts: np.ndarray, labels: list[str | None], tolerance_deg: float) -> list[str]:
    """One sentence per pose farther than ``tolerance_deg`` from its label."""
    return [f"pose {k} ({label}) rests {tilt:.1f} degrees from its label's direction (tolerance {tolerance_deg:g} "
            "degrees, [format] label_tolerance_deg): it was fitted as placed, not as labelled; check its label"
            for k, (tilt, label) in enumerate(zip(tilts.tolist(), labels)) if tilt > tolerance_deg]
