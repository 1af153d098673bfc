"""A continuous recording of the test plan: the table and the operator move
between segments while the logger keeps running.

Per axis: the static steps, each move between two steps recorded as motion
(a minimum-jerk move of ``step_move_s``); the table then accelerates at
``ramp_deg_s2`` into the first rate, ramps from rate to rate, ramps down to
rest after the last one and rests ``pause_s``; between axes the operator
turns the DUT by hand (``reorient_s``: a wobbling move with the hand's own
acceleration) into the next axis's starting orientation (theta = 0 of docs/conventions.md).

Angles are continuous through every transition. The plan's segments keep
their commanded angle labels; transitions carry none. The true rate (the
angle effects' rate factor, e.g. ``rate_error``) is folded in so that the
true angle stays continuous (docs/effects.md: the commanded angle becomes the
true angle within a rotation segment).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from rotcal.model.physics import Motion, axis_index, gravity_direction

if TYPE_CHECKING:
    from rotcal.simulate.spec import Plan

HAND_WOBBLE_DEG = 12.0         # largest excursion of the hand off the direct path
HAND_ACCELERATION = 0.6        # m/s^2, largest linear acceleration of a hand move


@dataclass(frozen=True, eq=False)
class HandMove:
    """Samples moved by hand: their gravity direction (unit, table frame,
    pointing up) and the hand's linear acceleration (m/s^2)."""

    mask: np.ndarray
    direction: np.ndarray
    acceleration: np.ndarray

    def specific_force(self, g_local: float) -> np.ndarray:
        return g_local * self.direction + self.acceleration


@dataclass(frozen=True)
class Phase:
    """One stretch of the recording, in table (true) time."""

    kind: str                 # step, move, ramp, rotation, pause, reorient
    axis: str | None
    t0_s: float
    t1_s: float
    theta0_deg: float = 0.0   # angle at t0 (commanded = true at t0)
    theta1_deg: float = 0.0   # move: target angle
    rate0_hz: float = 0.0     # ramp: start rate; rotation: the rate
    accel_deg_s2: float = 0.0  # ramp: signed angular acceleration
    rate_factor: float = 1.0  # rotation: the true rate is rate0 rate_factor (1 + rate_error)
    plan_segment: int | None = None

    @property
    def axis_idx(self) -> int:
        """The table axis turned in this phase (a reorientation by hand has none)."""
        if self.axis is None:
            raise ValueError(f"a {self.kind} phase turns no table axis")
        return axis_index(self.axis)

    @property
    def end_deg(self) -> float:
        """The true angle at t1."""
        d = self.t1_s - self.t0_s
        if self.kind == "move":
            return self.theta1_deg
        if self.kind == "ramp":
            return self.theta0_deg + 360.0 * self.rate0_hz * d + 0.5 * self.accel_deg_s2 * d * d
        if self.kind == "rotation":
            return self.theta0_deg + 360.0 * self.rate0_hz * self.rate_factor * d
        return self.theta0_deg


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """Fraction of a move done at normalised time tau in [0, 1] (zero speed
    and acceleration at both ends)."""
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def plan_phases(plan: Plan, rate_factor: float = 1.0) -> list[Phase]:
    """The continuous timeline of ``plan`` (true time from 0)."""
    dt = plan.dt_s
    steps = np.arange(0.0, 360.0, plan.step_deg)
    phases: list[Phase] = []
    t, seg = 0.0, 0

    def add(kind: str, axis: str | None, duration: float, **kw) -> Phase:
        nonlocal t
        phase = Phase(kind, axis, t, t + duration, **kw)
        phases.append(phase)
        t += duration
        return phase

    for i_axis, axis in enumerate(plan.axes):
        if i_axis:
            add("reorient", None, plan.reorient_s)
        for k, angle in enumerate(steps):
            add("step", axis, plan.step_samples * dt, theta0_deg=angle, plan_segment=seg)
            if k + 1 < steps.size:
                add("move", axis, plan.step_move_s, theta0_deg=angle, theta1_deg=steps[k + 1])
        seg += 1
        theta, rate = float(steps[-1]), 0.0
        for target in (*plan.rates_hz, 0.0):
            accel = np.sign(target - rate) * plan.ramp_deg_s2
            ramp = add("ramp", axis, 360.0 * abs(target - rate) / plan.ramp_deg_s2, theta0_deg=theta,
                       rate0_hz=rate, accel_deg_s2=accel)
            theta, rate = ramp.end_deg, target
            if target:
                rot = add("rotation", axis, plan.rotation_samples * dt, theta0_deg=theta, rate0_hz=target,
                          rate_factor=rate_factor, plan_segment=seg)
                theta, seg = rot.end_deg, seg + 1
        add("pause", axis, plan.pause_s, theta0_deg=theta)
    return phases


def _rotate(v: np.ndarray, axis: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
    """Rodrigues: rows of ``v`` rotated about ``axis`` by ``angle_deg`` (per row)."""
    k = axis / np.linalg.norm(axis)
    a = np.deg2rad(angle_deg)[:, None]
    return v * np.cos(a) + np.cross(k, v) * np.sin(a) + np.outer(v @ k, k) * (1.0 - np.cos(a))


def _hand_path(start: np.ndarray, end: np.ndarray, tau: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Gravity directions and linear accelerations of one hand move from
    ``start`` to ``end`` (unit vectors) at normalised times ``tau``."""
    axis = np.cross(start, end)
    if np.linalg.norm(axis) < 1e-9:
        axis = np.cross(start, rng.standard_normal(3))
    total_deg = np.degrees(np.arccos(np.clip(start @ end, -1.0, 1.0)))
    path = _rotate(np.tile(start, (tau.size, 1)), axis, total_deg * minimum_jerk(tau))
    wobble_deg = (HAND_WOBBLE_DEG * rng.uniform(0.5, 1.0) * np.sin(np.pi * tau) ** 2
                  * np.sin(2 * np.pi * rng.uniform(1.0, 2.5) * tau))
    direction = _rotate(path, rng.standard_normal(3), wobble_deg)
    lin_dir = rng.standard_normal(3)
    lin_dir /= np.linalg.norm(lin_dir)
    acceleration = HAND_ACCELERATION * np.outer(np.sin(2 * np.pi * tau) * np.sin(np.pi * tau) ** 2, lin_dir)
    return direction, acceleration


def schedule_continuous(plan: Plan, rate_factor: float, rng: np.random.Generator
                        ) -> tuple[Motion, pl.DataFrame, list[Phase], HandMove]:
    """Samples every ``dt_s`` from 0 through the whole timeline: the table's
    motion, the plan labels (null in transitions) and the hand moves."""
    phases = plan_phases(plan, rate_factor)
    dt_ns = int(round(plan.dt_s * 1e9))
    t_ns = np.arange(0, int(phases[-1].t1_s * 1e9), dt_ns, dtype=np.int64)
    t_s = t_ns / 1e9
    which = np.searchsorted([p.t0_s for p in phases], t_s, side="right") - 1
    n = t_s.size
    axis_idx = np.zeros(n, int)
    theta = np.zeros(n)
    theta_cmd = np.zeros(n)
    t_start = np.zeros(n)
    rate = np.zeros(n)
    rotating = np.zeros(n, bool)
    hand_dir, hand_acc = np.zeros((n, 3)), np.zeros((n, 3))
    label_axis = np.full(n, None, dtype=object)
    label_rate = np.full(n, np.nan)
    label_angle = np.full(n, np.nan)
    plan_segment = np.full(n, -1)
    end_direction = np.zeros(3)  # every phase sets it; the first phase is never a reorientation
    for k, p in enumerate(phases):
        on = which == k
        tau_s = t_s[on] - p.t0_s
        if p.kind == "reorient":
            start = end_direction
            nxt = phases[k + 1]
            end = gravity_direction(np.array([nxt.axis_idx]), np.array([nxt.theta0_deg]))[0]
            hand_dir[on], hand_acc[on] = _hand_path(start, end, tau_s / (p.t1_s - p.t0_s), rng)
            continue
        axis_idx[on] = p.axis_idx
        if p.kind == "move":
            theta[on] = p.theta0_deg + (p.theta1_deg - p.theta0_deg) * minimum_jerk(tau_s / (p.t1_s - p.t0_s))
        elif p.kind == "ramp":
            theta[on] = p.theta0_deg + 360.0 * p.rate0_hz * tau_s + 0.5 * p.accel_deg_s2 * tau_s**2
        elif p.kind == "rotation":
            rotating[on] = True
            theta_cmd[on] = p.theta0_deg + 360.0 * p.rate0_hz * tau_s
            t_start[on], rate[on] = p.t0_s, p.rate0_hz
        else:
            theta[on] = p.theta0_deg
        if p.kind in ("step", "rotation"):
            label_axis[on] = p.axis
            label_rate[on] = p.rate0_hz
            label_angle[on] = theta_cmd[on] if p.kind == "rotation" else p.theta0_deg
            plan_segment[on] = p.plan_segment
        end_direction = gravity_direction(np.array([p.axis_idx]), np.array([p.end_deg]))[0]
    theta_cmd = np.where(rotating, theta_cmd, theta)
    motion = Motion(t_s=t_s, axis_idx=axis_idx, rotating=rotating, theta_cmd_deg=theta_cmd,
                    t_start_s=t_start, rate_hz=rate, t0_s=0.0)
    labels = pl.DataFrame({
        "t_ns": t_ns,
        "axis": pl.Series(label_axis.tolist(), dtype=pl.String),
        "rate_hz": pl.Series(label_rate).fill_nan(None),
        "angle_deg": pl.Series(label_angle).fill_nan(None),
        "plan_segment": pl.Series(plan_segment, dtype=pl.Int32).replace(-1, None),
    })
    hand = which == np.array([k for k, p in enumerate(phases) if p.kind == "reorient"] or [-1])[:, None]
    mask = hand.any(axis=0)
    return motion, labels, phases, HandMove(mask, hand_dir[mask], hand_acc[mask])


def timeline(phases: list[Phase], clock_factor: float = 1.0) -> list[dict]:
    """The phases as truth.json records, times on the logger's clock."""
    return [{"kind": p.kind, "axis": p.axis, "rate_hz": p.rate0_hz if p.kind == "rotation" else 0.0,
             "t_start_s": p.t0_s * clock_factor, "t_end_s": p.t1_s * clock_factor, "plan_segment": p.plan_segment}
            for p in phases]

