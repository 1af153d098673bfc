"""The noise stage: each channel's noise model identified from the
residuals of the fitted model (``residuals``), by its Allan variance
(``allan``) fitted with the IEEE Std 952 / 1293 terms (``model``); the
``noise`` table (schemas/noise.json)."""

from __future__ import annotations

from dataclasses import dataclass

import polars as pl

from rotcal.model.physics import CHANNELS
from rotcal.noise.allan import AllanVariance, PooledAllan, pooled_avar, pooled_avars
from rotcal.noise.model import ChannelNoise, Term, identify_channel
from rotcal.noise.residuals import residual_pieces, sample_interval_s

__all__ = ["AllanVariance", "ChannelNoise", "FittedNoise", "NoiseModel", "Term", "calibration_noise", "identify_noise", "noise_frame",
           "pooled_avar"]

METHOD = ("overlapping Allan variance of the fitted model's residuals at octave averaging times, fitted with the "
          "IEEE Std 952 / 1293 terms by weighted least squares (each tau weighted by its equivalent degrees of freedom)")


@dataclass(frozen=True, eq=False)
class NoiseModel:
    """The recording's noise: per channel its Allan variance and model, the
    sample interval (s) and the output unit."""

    channels: tuple[ChannelNoise, ...]
    dt_s: float
    output_unit: str


def identify_noise(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame, dwells: pl.DataFrame,
                   output_unit: str, fitted: FittedNoise | None = None) -> NoiseModel:
    """Each channel's noise model from the residuals of the fitted model;
    ``fitted``: the fitted segments' pieces already pooled where the samples
    were read block by block (``samples`` then holds the rest)."""
    dt = sample_interval_s(samples) if fitted is None else fitted.dt_s
    if dt <= 0:
        return NoiseModel((), 0.0, output_unit)
    if fitted is None:
        pieces = residual_pieces(samples, segments, fits, dwells, dt)
        allan = pooled_avars(pieces, 1 / dt) if pieces else [None] * len(CHANNELS)
        return NoiseModel(tuple(identify_channel(c, [p[:, r] for p in pieces], 1 / dt, output_unit, allan[r])
                                for r, c in enumerate(CHANNELS)), dt, output_unit)
    # the poses' pieces, after the fitted segments' (and the dwells where those give none), as held whole
    rest = residual_pieces(samples, segments, fits.clear(), dwells if not fitted.pooled.sizes else dwells.clear(), dt)
    for piece in rest:
        fitted.pooled.add(piece)  # the caller's copy (``blockwise.segments.StreamedSegments.noise_pooled``)
    sizes = fitted.pooled.sizes
    allan = fitted.pooled.result(1 / dt) if sizes else [None] * len(CHANNELS)
    return NoiseModel(tuple(identify_channel(c, [], 1 / dt, output_unit, allan[r], sizes) if sizes else
                            identify_channel(c, [], 1 / dt, output_unit) for r, c in enumerate(CHANNELS)), dt, output_unit)


@dataclass(eq=False)
class FittedNoise:
    """The fitted segments' residual pieces pooled as a capture read block
    by block gives them (``allan.PooledAllan``), at the recording's sample
    interval ``dt_s`` (``residuals.sample_interval_s`` of every sample)."""

    dt_s: float
    pooled: PooledAllan


def noise_frame(model: NoiseModel, dataset: str) -> pl.DataFrame:
    """The ``noise`` table: one row per channel and term (schemas/noise.json)."""
    rows = [{"dataset": dataset, "channel": ch.channel, "term": t.term, "index": t.index, "value": t.value, "u": t.u,
             "dof": t.dof, "unit": t.unit, "chi2_reduced": ch.chi2_reduced, "sample_interval_s": model.dt_s}
            for ch in model.channels for t in ch.terms]
    schema = {"dataset": pl.String, "channel": pl.String, "term": pl.String, "index": pl.Int32, "value": pl.Float64,
              "u": pl.Float64, "dof": pl.Float64, "unit": pl.String, "chi2_reduced": pl.Float64,
              "sample_interval_s": pl.Float64}
    return pl.DataFrame(rows, schema=schema)


def calibration_noise(model: NoiseModel) -> dict | None:
    """The noise model as ``calibration.json`` holds it (schemas/calibration.json ``noise``); None without channels."""
    if not model.channels:
        return None
    return {"method": METHOD, "sample_interval_s": model.dt_s, "channels": [
        {"channel": ch.channel, "chi2_reduced": ch.chi2_reduced, **({"reason": ch.reason} if ch.reason else {}),
         "terms": [{"term": t.term, "index": t.index, "value": t.value, "std_uncertainty": t.u, "dof": t.dof,
                    "unit": t.unit} for t in ch.terms]} for ch in model.channels]}
