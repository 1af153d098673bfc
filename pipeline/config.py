"""The run configuration, resolved once from ``configs/defaults.toml`` and an
optional ``--config`` file into a frozen record."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import jsonschema

from rotcal.errors import ConfigError
from rotcal.tables import schema_text


@dataclass(frozen=True)
class Limits:
    """Safety limits on inputs: beyond them a file is refused, in bounded memory."""

    max_line_bytes: int = 1_048_576
    max_mcap_record_bytes: int = 268_435_456
    max_dataset_toml_bytes: int = 1_048_576


@dataclass(frozen=True)
class BatchConfig:
    """``rotcal batch``: how many datasets run at once, and where."""

    workers: int = 0  # local worker processes; 0 = one per core
    executor: str = "local"  # or dask://HOST:PORT, an existing Dask scheduler


@dataclass(frozen=True)
class FitConfig:
    min_samples: int = 10
    min_span_deg: float = 30.0
    sine_fit: str = "three_parameter"


@dataclass(frozen=True)
class UncertaintyConfig:
    """GUM Supplement 1 Monte Carlo propagation beside the first-order one."""

    monte_carlo: bool = False
    monte_carlo_max_draws: int = 1_000_000
    monte_carlo_seed: int = 1


@dataclass(frozen=True)
class DiagnosisConfig:
    """The model-mismatch diagnosis: whether it runs and its false-alarm rates."""

    enabled: bool = True
    false_alarm: float = 1e-4             # per catalogue extension (per axis or channel) and per scan for a step
    unexplained_false_alarm: float = 1e-3  # per family of residual scans
    report: bool = True                   # write report.md with figures
    max_samples: int = 100_000            # samples modelled; longer segments are thinned evenly beyond it


@dataclass(frozen=True)
class ReportConfig:
    """Outputs for people beside the tables."""

    figures: bool = True  # PNG figures: the frequency response, the diagnosis report's residual plots


@dataclass(frozen=True)
class RunConfig:
    workers: int = 0
    fit: FitConfig = field(default_factory=FitConfig)
    limits: Limits = field(default_factory=Limits)
    diagnosis: DiagnosisConfig = field(default_factory=DiagnosisConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    batch: BatchConfig = field(default_factory=BatchConfig)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    source: str | None = None


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _check(doc: dict, path: str) -> None:
    errors = list(jsonschema.Draft202012Validator(schema_text("run_config")).iter_errors(doc))
    if errors:
        err = errors[0]
        where = ".".join(str(p) for p in err.absolute_path) or "top level"
        raise ConfigError(f"invalid configuration at {where}: {err.message}", path=path)


def load_config(path: Path | None = None) -> RunConfig:
    """Defaults from ``configs/defaults.toml``, overridden by ``path``."""
    doc = tomllib.loads(resources.files("rotcal_configs").joinpath("defaults.toml").read_text())
    if path is not None:
        try:
            over = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError("configuration file not found", path=path) from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"configuration is not valid TOML: {exc}", path=path) from None
        _check(over, str(path))
        doc = _merge(doc, over)
    _check(doc, str(path or "configs/defaults.toml"))
    run = doc.get("run", {})
    return RunConfig(
        workers=run.get("workers", 0),
        fit=FitConfig(**doc.get("fit", {})),
        limits=Limits(**doc.get("limits", {})),
        diagnosis=DiagnosisConfig(**doc.get("diagnosis", {})),
        report=ReportConfig(**doc.get("report", {})),
        batch=BatchConfig(**doc.get("batch", {})),
        uncertainty=UncertaintyConfig(**doc.get("uncertainty", {})),
        source=None if path is None else str(path),
    )
