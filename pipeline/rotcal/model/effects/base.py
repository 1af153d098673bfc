"""What one effect of the catalogue is: its name, parameters with units,
sizes to test, its term of the forward model, its simulator option, its
diagnosis model and its finding sentence.

An effect is a subclass of one of the forward model's stages (the order of
docs/effects.md, "The order of the forward model"):

1. ``AngleEffect``: the commanded angle becomes the true angle (a rate
   factor, an added angle term) on rotation segments;
2. ``SamplingEffect``: each channel's true sampling instant;
3. ``GravityEffect`` then ``ForceEffect``: the specific force a, gravity
   first, then added terms;
4. ``GainEffect``: a per-channel factor f(u) on the offset-free output
   y = r . a, u = y / x1g; then ``ScaleEffect``: a per-sample, per-channel
   factor that does not depend on y (a sensitivity that follows the
   temperature);
5. ``OffsetEffect``: a term added to the offsets;
6. ``LimitEffect``: output limits, after noise and rounding.

Its *state* is what the forward model needs of it (an effect's own type:
a per-channel array, a dict axis index -> values, a number, a pair of
limits); the simulator builds it from the option ``NAME:key=value``, the
diagnosis from its fitted internal parameters (``state_from``).

An effect may act in two stages (a subclass of both, e.g. a ``ScaleEffect``
and an ``OffsetEffect``): each stage reads its own part of the one state,
and the effect's place in the catalogue is its first stage's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Protocol

import numpy as np

from rotcal.errors import ConfigError
from rotcal.model.conventions import AXES, Motion

ALL = (0, 1, 2)  # a parameter that enters every channel's equation


@dataclass(frozen=True)
class Parameter:
    """A parameter as docs/effects.md names it, with its unit ("output unit" is
    the dataset's) and meaning."""

    name: str
    unit: str
    meaning: str


@dataclass(frozen=True)
class Candidate:
    """One extension of the diagnosis's model: ``effect`` (a catalogue name,
    or ``unexplained``) on ``scope`` (an axis, a channel, or '' for the
    whole dataset), with its internal parameter names and, per parameter,
    the channels whose equation it enters."""

    effect: str
    scope: str
    names: tuple[str, ...]
    channels: tuple[tuple[int, ...], ...]

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.scope}" if self.scope else self.effect


@dataclass(frozen=True)
class Support:
    """The samples on which an extension's Jacobian columns can be nonzero:
    those of one table ``axis`` (None: every sample), only its rotating ones
    if ``rotating``. The model computes the columns and their normal
    equations there alone (``rotcal.diagnose.design``)."""

    axis: int | None = None
    rotating: bool = False


EVERYWHERE = Support()


def on_runs(runs: list[tuple[int, slice]], first: np.ndarray, *factors: np.ndarray,
            out: np.ndarray | None = None) -> np.ndarray:
    """first times ``factors`` per sample, multiplied in that order, on
    ``runs`` (rate, samples) alone: into ``out`` if given (it may be
    ``first``; left as it is off the runs), else a new array, zero there."""
    out = np.zeros(first.size) if out is None else out
    for _, at in runs:
        product = out[at]
        np.multiply(first[at], factors[0][at], out=product)
        for factor in factors[1:]:
            product *= factor[at]
    return out


@dataclass(frozen=True)
class ReportedParameter:
    name: str
    value: float
    std_uncertainty: float
    unit: str


class Channel(Protocol):
    """One channel's model quantities at the current estimate, per sample
    (``rotcal.diagnose.model.ChannelState``): what a Jacobian column is made of."""

    @property
    def r(self) -> int: ...
    @property
    def y(self) -> np.ndarray: ...         # offset-free linear output
    @property
    def u(self) -> np.ndarray: ...         # y / x1g
    @property
    def slope(self) -> np.ndarray: ...     # d output / d y
    @property
    def d_theta(self) -> np.ndarray: ...   # d output / d theta, per degree
    @property
    def theta(self) -> np.ndarray: ...     # true angle at the channel's sampling instant
    @property
    def up(self) -> np.ndarray: ...        # gravity's direction there, (3, n) per component (Geist 2017 Eq. 5)
    @property
    def base(self) -> np.ndarray: ...      # the rotating samples' uniform angle (before ripple)
    @property
    def stretch(self) -> np.ndarray: ...   # d theta / d base
    @property
    def gained(self) -> np.ndarray: ...    # y times every gain effect's factor: what the scale effects multiply
    @property
    def unit_slope(self) -> bool: ...      # ``slope`` is 1 everywhere

    def responsivity_dot(self, vectors: np.ndarray, out: np.ndarray | None = None,
                         runs: list[tuple[int, slice]] | None = None) -> np.ndarray: ...
    # R_row . vectors per sample, vectors (3, n) per component (into ``out`` if given; if ``runs``
    # (rate, samples) are given, on them alone: ``out`` left as it is off them, a new array zero)

    def responsivity_times(self, j: int, values: np.ndarray, out: np.ndarray | None = None,
                           runs: list[tuple[int, slice]] | None = None) -> np.ndarray: ...
    # the responsivity row's component j (output unit per g) times ``values`` per sample (``runs`` as above)


class ColumnContext(Protocol):
    """What a Jacobian column may use besides its channel: the motion, the
    current effects, and a cache of channel-independent factors."""

    motion: Motion
    g_local: float
    effects: Any           # rotcal.model.effects.Effects
    on_axis: list[np.ndarray]

    def cached(self, key: object, make: Callable[[], np.ndarray]) -> np.ndarray: ...

    def runs(self, support: Support) -> list[tuple[int, slice]]: ...
    # (rate index, samples) of the runs of one rate and axis that hold ``support``'s samples

    def gain_column(self, effect: GainEffect, st: Channel, out: np.ndarray | None = None) -> np.ndarray: ...

    def scale_column(self, effect: ScaleEffect, st: Channel, derivative: np.ndarray,
                     out: np.ndarray | None = None) -> np.ndarray: ...


def scope_rank(scope: str) -> int:
    """Order of a candidate's scope: the whole dataset, then x or u, y or v, z or w."""
    return "xyzuvw".index(scope) % 3 if scope else -1


class Effect:
    """One physics of docs/effects.md. Subclasses set the class attributes and
    override the hooks of their stage, the simulator and the diagnosis."""

    name: ClassVar[str]
    physics: ClassVar[str]                      # what happens, and the model's term
    parameters: ClassVar[tuple[Parameter, ...]]
    options: ClassVar[frozenset[str]]           # keys of the simulator option NAME:key=value
    sizes: ClassVar[tuple[float, float]]        # the size range to test on the default plan
    size_of: ClassVar[str]                      # what ``sizes`` measures
    where: ClassVar[str]                        # the finding's location, ``{s}`` the scope
    # Its row in docs/effects.md's table: the diagnosis table lists effects in this order.
    listed: ClassVar[int] = 1000
    # Where its parameters sit in the diagnosis's parameter vector (candidates sort by
    # (slot, scope, listed)): the order the solver has always used, so every figure
    # stays bit-identical; a new effect's parameters go last.
    slot: ClassVar[int] = 1000
    # Option keys of which a request must give at least one (its size: an
    # effect asked for with none of them would be simulated as absent), and
    # option keys that are magnitudes, never negative. Empty ``sizes_given``
    # means every option but ``axis``.
    sizes_given: ClassVar[frozenset[str]] = frozenset()
    magnitudes: ClassVar[frozenset[str]] = frozenset()
    # Per-sample observations besides t, u, v, w and the table's labels that
    # the diagnosis needs to test it (e.g. ``temperature_c``): on a dataset
    # without them it is neither tested nor listed.
    needs: ClassVar[frozenset[str]] = frozenset()
    # What a DUT at rest shows of it, for the static diagnosis (``rotcal.diagnose.static``):
    # None, nothing; "pose", the pose means alone; "time", the means with their time stamps;
    # "temperature", the means at a varying temperature (its residuals are drawn against that
    # quantity, against the channel's output otherwise). ``at_rest_steps``: the central-difference
    # step of its internal parameters there, by name prefix (a parameter's typical size), and
    # ``not_at_rest`` why static poses leave it untested when ``at_rest`` is None.
    at_rest: ClassVar[Literal["pose", "time", "temperature"] | None] = None
    at_rest_steps: ClassVar[Mapping[str, float]] = {}
    not_at_rest: ClassVar[str] = "static poses do not show it (it needs rotation, a table angle or time stamps)"
    # A rotation fitted against its own phase absorbs it (the fitted rate is the true one,
    # ``rotcal.diagnose.reconstructed``): not tested on angles reconstructed from solved phases.
    absorbed_by_own_phase: ClassVar[bool] = False

    # --- the simulator -------------------------------------------------
    def complete(self, params: dict, rng: np.random.Generator) -> dict:
        """The option's parameters checked and completed (random where the
        request leaves a choice, drawn from ``rng``)."""
        unknown = sorted(set(params) - self.options)
        if unknown:
            raise ConfigError(f"effect {self.name}: unknown parameter {unknown[0]!r} (known: {', '.join(sorted(self.options))})")
        sizes = self.sizes_given or self.options - {"axis"}
        if not sizes & set(params):
            raise ConfigError(f"effect {self.name}: give its size, one of {', '.join(sorted(sizes))}")
        negative = sorted(k for k in self.magnitudes & set(params) if float(params[k]) < 0)
        if negative:
            raise ConfigError(f"effect {self.name}: {negative[0]} = {params[negative[0]]} is a magnitude and cannot be negative")
        return dict(params)

    def need_axis(self, params: dict) -> str:
        axis = str(params.get("axis"))
        if axis not in AXES:
            raise ConfigError(f"effect {self.name} needs axis=x, y or z")
        return axis

    def state(self, previous: Any, params: dict) -> Any:
        """The forward model's state from completed parameters; ``previous``
        is the state of earlier requests of the same effect (or None)."""
        raise NotImplementedError

    def resolve(self, params: dict, clean: np.ndarray) -> bool:
        """Fill in parameters that depend on the noise-free output (in place);
        True when the state must be rebuilt from them."""
        return False

    def temperature_history(self, params: dict, motion: Motion) -> np.ndarray | None:
        """The DUT temperature per sample (degree C) this effect's request
        makes the simulator record as ``temperature_c`` (None: none)."""
        return None

    def draw(self, size: float, sign: float, axis: str, channel: str, rng: np.random.Generator) -> str:
        """A request of ``size`` (drawn within ``sizes``) in the option form."""
        raise NotImplementedError

    # --- the diagnosis -------------------------------------------------
    def candidates(self, rotating_axes: tuple[str, ...], all_axes: tuple[str, ...],
                   angles_measured: bool) -> tuple[Candidate, ...]:
        """Its model extensions testable on a dataset with these segments."""
        return ()

    def state_from(self, values: dict[str, Any]) -> Any:
        """The state from internal parameter values (None: not modelled)."""
        return None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d output / d (internal parameter ``name``) in channel ``st.r``;
        ``out`` (n,), when given, may hold the result (the design's row:
        the diagnosis then copies nothing), which is returned either way;
        written there on the column's ``support`` alone (the design reads
        nothing else), a new array is zero off it."""
        raise NotImplementedError

    def support(self, cand: Candidate) -> Support:
        """Where ``cand``'s columns can be nonzero (exactly zero elsewhere)."""
        return EVERYWHERE

    def report(self, cand: Candidate, value: np.ndarray, cov: np.ndarray, output_unit: str) -> list[ReportedParameter]:
        """The docs/effects.md parameters of a fitted extension, with uncertainties."""
        units = {p.name: p.unit.replace("output unit", output_unit) for p in self.parameters}
        u = np.sqrt(np.diag(cov))
        return [ReportedParameter(n, float(v), float(s), units[n]) for n, v, s in zip(cand.names, value, u)]


class AngleEffect(Effect):
    """Stage 1: the true angle of rotation samples."""

    def rate_factor(self, state: Any) -> float:
        """The true rate over the commanded one."""
        return 1.0

    def angle(self, state: Any, motion: Motion, base: np.ndarray) -> np.ndarray | None:
        """Added to ``base``, the rotating samples' uniform true angle (degree)."""
        return None

    def angle_slope(self, state: Any, motion: Motion, base: np.ndarray) -> np.ndarray | None:
        """d angle / d base, the derivative of ``angle``."""
        return None


class SamplingEffect(Effect):
    """Stage 2: the true sampling instant of each channel."""

    def delays(self, state: Any) -> np.ndarray:
        """Per channel, seconds after the stamp."""
        raise NotImplementedError


class ForceEffect(Effect):
    """Stage 3b: terms added to the specific force (table frame, m/s^2)."""

    def force(self, state: Any, motion: Motion, a: np.ndarray, g_local: float, rate_factor: float) -> None:
        """Change ``a`` (n, 3) in place."""
        raise NotImplementedError

    def angle_scale(self, state: Any, motion: Motion) -> np.ndarray | None:
        """Factor of d a / d theta per sample (None: 1)."""
        return None


class GravityEffect(ForceEffect):
    """Stage 3a: gravity's part of the specific force, before added terms."""


class GainEffect(Effect):
    """Stage 4: y -> y f(u) per channel, u = y / x1g; the state is the
    per-channel coefficient k (3,)."""

    def gain(self, k: Any, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def chain(self, k: float, S: np.ndarray, P: np.ndarray, u: np.ndarray) -> np.ndarray:
        """d(y P f)/dy from S = d(y P)/dy and the product P of the earlier
        factors: S f + P u f'(u) (the product rule, one factor at a time)."""
        raise NotImplementedError

    def gain_derivative(self, u: np.ndarray) -> np.ndarray:
        """d f / d k."""
        raise NotImplementedError

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        return ctx.gain_column(self, st, out)


class ScaleEffect(Effect):
    """Stage 4b: y -> y f(u) s per channel, s a factor per sample that
    does not depend on y (e.g. a sensitivity following the temperature)."""

    def scale(self, state: Any, motion: Motion) -> np.ndarray:
        """The factor (n, 3)."""
        raise NotImplementedError


class OffsetEffect(Effect):
    """Stage 5: a term added to the offsets (n, 3)."""

    def offset(self, state: Any, motion: Motion) -> np.ndarray:
        raise NotImplementedError


class LimitEffect(Effect):
    """Stage 6: output limits (after noise and rounding). The diagnosis
    finds them from runs of stuck samples (``rotcal.diagnose.clipping``),
    not by a model extension."""

    def limits(self, state: Any) -> tuple[float | None, float | None]:
        raise NotImplementedError


# The forward model's stages in their order (a GravityEffect is also a ForceEffect: it comes first).
STAGES: tuple[type[Effect], ...] = (AngleEffect, SamplingEffect, GravityEffect, ForceEffect, GainEffect, ScaleEffect,
                                    OffsetEffect, LimitEffect)


def stage_rank(effect: Effect) -> int:
    return next(i for i, stage in enumerate(STAGES) if isinstance(effect, stage))
