"""What the user states about hand-placed poses (``[device] cross_axis``,
``sensitivity``, ``sensitivity_tolerance``, ``offset_tolerance``,
``[format] label_tolerance_deg`` and ``pose_means`` of dataset.toml), read by the static
reduction (``combine.placement``). Imports nothing heavy: ``ingest.meta``
builds it when reading a dataset's metadata."""

from __future__ import annotations

import math
from dataclasses import dataclass

# typical consumer MEMS datasheets state cross-axis sensitivity of 1 to 2 % (docs/method.md, "Datasheet priors")
DEFAULT_CROSS_AXIS = 0.02
DEFAULT_TOLERANCE_DEG = 4.0  # a hand places a face within about 3 degrees (docs/method.md, "Recording by hand")


@dataclass(frozen=True)
class Placement:
    """What the user states about the poses: the datasheet's cross-axis
    sensitivity bound (fraction; None: not stated, ``DEFAULT_CROSS_AXIS``
    taken), the tolerance of pose labels (degrees) and whether each row of
    the capture is a pose mean."""

    cross_axis: float | None = None
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG
    pose_means: bool = False  # each row of the capture is one pose's mean (``[format] pose_means``)
    # the datasheet's bounds ([device]; ``combine.datasheet``): nominal sensitivity (output unit per standard g),
    # its tolerance (fraction) and the zero-g offset's (output units, one or one per axis)
    sensitivity: float | None = None
    sensitivity_tolerance: float | None = None
    offset_tolerance: float | tuple[float, ...] | None = None

    @property
    def misalignment_u(self) -> float:
        """The standard uncertainty of cos(phi) for an angle the data do not
        determine: the bound as a rectangular distribution (GUM 4.3.7)."""
        return (DEFAULT_CROSS_AXIS if self.cross_axis is None else self.cross_axis) / math.sqrt(3.0)

    @property
    def stated_u(self) -> float:
        """``misalignment_u`` where ``[device] cross_axis`` states the bound, else 0 (no prior on fitted angles)."""
        return self.misalignment_u if self.cross_axis is not None else 0.0

    @property
    def prior_note(self) -> str:
        source = "[device] cross_axis" if self.cross_axis is not None else "not stated in [device] cross_axis, default"
        bound = DEFAULT_CROSS_AXIS if self.cross_axis is None else self.cross_axis
        return (f"the poses do not determine the angles between the axes: the offsets and sensitivities carry a "
                f"Type B input for them (cross-axis bound {100 * bound:g} %, {source}; u(cos phi) = "
                f"{self.misalignment_u:.3g}, rectangular)")


