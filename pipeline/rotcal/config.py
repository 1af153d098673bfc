"""The run configuration: one definition of every key, its default, its
bounds and its meaning, from which the rest is made.

``RunConfig`` mirrors a ``--config`` TOML file: one field per table, each
table a frozen pydantic dataclass whose fields carry the default, the bounds
(``Field``; every number finite) and a one-line description. From it come

- the defaults (a key a file leaves out keeps its default),
- the validation of a file and of command-line options (``load_config``,
  ``with_options``): a one-line ``ConfigError`` naming the file and the key,
- ``schemas/run_config.json`` and ``configs/defaults.toml``, written by
  ``python -m rotcal.config`` (run in the checkout) and compared with the
  committed files by ``tests/test_config.py``.
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, ConfigDict, Field, TypeAdapter, ValidationError
from pydantic.dataclasses import dataclass
from pydantic.json_schema import GenerateJsonSchema
from pydantic_core import PydanticCustomError

from rotcal.errors import ConfigError

SCHEMA_VERSION = "1.3"  # 1.2: non-finite numbers refused; 1.3: [report] pdf, paper, site
# ``batch.executor``: the local process pool, or an existing Dask scheduler (group 1: its address)
EXECUTOR = re.compile(r"local|dask://([^/\s]+:[0-9]+)")

# Unknown keys are refused; NaN and infinity are refused wherever a number is.
_TABLE = ConfigDict(extra="forbid", allow_inf_nan=False)


def _key(default: Any, description: str, **bounds: Any) -> Any:
    """A key of the file: its default, description and bounds; numbers and
    booleans strict (no string read as a number, no number as a boolean)."""
    return Field(default, description=description, strict=isinstance(default, int | float) or None, **bounds)


def _executor(value: str) -> str:
    if not EXECUTOR.fullmatch(value):
        raise PydanticCustomError("executor", "executor '{value}' is not 'local' or 'dask://HOST:PORT'", {"value": value})
    return value


@dataclass(frozen=True, config=_TABLE)
class RunSection:
    """``rotcal run``: how many cores one run may use, and whether captures may be read whole (a check)."""

    workers: int = _key(0, "cores one run uses for its threads (segment fits, MCAP decompression); 0 = every core it may run on", ge=0)
    stream_above_samples: int = _key(
        0, "0: every capture the block path takes is read block by block (docs/streaming.md lists what it does not "
        "take); N > 0: captures of at most N samples are read whole instead, as a check", ge=0)


@dataclass(frozen=True, config=_TABLE)
class FitConfig:
    """The per-segment fits."""

    min_samples: int = _key(10, "fewer samples in a segment: a failure row, not a fit", ge=4)
    min_span_deg: float = _key(30.0, "smallest angle range a segment must cover", ge=0)
    sine_fit: Literal["three_parameter", "four_parameter"] = _key(
        "three_parameter", "rotation segments: three_parameter (rate as commanded) or four_parameter "
        "(IEEE Std 1057: the rate fitted too, for an untrusted rate)")


@dataclass(frozen=True, config=_TABLE)
class UncertaintyConfig:
    """GUM Supplement 1 Monte Carlo propagation beside the first-order one."""

    monte_carlo: bool = _key(False, "GUM Supplement 1 Monte Carlo beside the first-order propagation")
    monte_carlo_max_draws: int = _key(1_000_000, "adaptive: batches of 10^4 until stable (GUM S1 7.9), at most this many", ge=20_000)
    monte_carlo_seed: int = _key(1, "seed of the Monte Carlo draws", ge=0)


@dataclass(frozen=True, config=_TABLE)
class ReportConfig:
    """Outputs for people beside the tables."""

    figures: bool = _key(True, "PNG figures (frequency response, diagnosis residuals); rotcal batch draws them only with --figures")
    pdf: bool = _key(True, "certificate.pdf beside certificate.html (docs/outputs.md, the certificate); rotcal batch writes it only with --pdf")
    paper: Literal["a4", "letter"] = _key("a4", "the PDF certificate's paper: a4 or letter")
    site: str = _key("", "the laboratory's site file (its [laboratory], [equipment], [certificate] defaults); "
                     "empty: site.toml beside the dataset (rotcal run) or in ROOT (rotcal batch), if there is one")


@dataclass(frozen=True, config=_TABLE)
class Limits:
    """Safety limits on inputs: beyond them a file is refused, in bounded memory."""

    max_line_bytes: int = _key(1_048_576, "longest CSV line accepted", ge=64)
    max_mcap_record_bytes: int = _key(268_435_456, "largest MCAP record (chunk) accepted", ge=1024)
    max_dataset_toml_bytes: int = _key(1_048_576, "largest dataset.toml rotcal batch reads", ge=64)


@dataclass(frozen=True, config=_TABLE)
class DiagnosisConfig:
    """The model-mismatch diagnosis: whether it runs and its false-alarm rates."""

    enabled: bool = _key(True, "run the model-mismatch diagnosis after the baseline fit")
    false_alarm: float = _key(1e-4, "per catalogue test (one effect on one axis or channel) and for an offset step", gt=0, le=0.5)
    unexplained_false_alarm: float = _key(
        1e-3, "per family of residual scans (tones, harmonics, misfits, Appendix B, rate dependence)", gt=0, le=0.5)
    report: bool = _key(True, "write report.md and its figures")
    max_samples: int = _key(
        100_000, "samples modelled; beyond, long segments are thinned evenly (noise grows as sqrt of the thinning)", ge=1000)


@dataclass(frozen=True, config=_TABLE)
class BatchConfig:
    """``rotcal batch``: how many datasets run at once, and where."""

    workers: int = _key(0, "cores in all, shared by the datasets processed at once on the local pool; 0 = every core it may run on", ge=0)
    executor: Annotated[str, AfterValidator(_executor)] = _key(
        "local", "or dask://HOST:PORT: an existing Dask distributed scheduler", json_schema_extra={"pattern": f"^({EXECUTOR.pattern})$"})


@dataclass(frozen=True, config=_TABLE)
class RunConfig:
    """The whole configuration: one field per table of the file."""

    run: RunSection = Field(default_factory=RunSection)
    fit: FitConfig = Field(default_factory=FitConfig)
    uncertainty: UncertaintyConfig = Field(default_factory=UncertaintyConfig)
    report: ReportConfig = Field(default_factory=ReportConfig)
    limits: Limits = Field(default_factory=Limits)
    diagnosis: DiagnosisConfig = Field(default_factory=DiagnosisConfig)
    batch: BatchConfig = Field(default_factory=BatchConfig)


def _validated(doc: dict, path: str | Path | None) -> RunConfig:
    """``doc`` (tables of keys) as a ``RunConfig``; the first fault as a one-line ``ConfigError``."""
    try:
        return RunConfig(**doc)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "top level"
        problem = {"unexpected_keyword_argument": "unknown key", "dataclass_type": "not a table"}.get(err["type"], err["msg"])
        raise ConfigError(f"invalid configuration at {where}: {problem}", path=path) from None


def load_config(path: Path | None = None) -> RunConfig:
    """The defaults, overridden by the keys of the TOML file ``path``."""
    if path is None:
        return RunConfig()
    return _validated(read_toml(path, "configuration file"), path)


def read_toml(path: Path, what: str) -> dict[str, Any]:
    """A TOML file of options (the run configuration, a simulation request);
    a missing or malformed file is a one-line ``ConfigError`` naming ``what``."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{what} not found", path=path) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} is not valid TOML: {exc}", path=path) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} is not UTF-8 text: {exc}", path=path) from None
    except OSError as exc:  # a directory, no permission
        raise ConfigError(f"{what} cannot be read: {exc.strerror}", path=path) from None
    except (RecursionError, ValueError):  # nesting beyond the parser's recursion; int() of thousands of digits
        raise ConfigError(f"{what} is not valid TOML: tables nested too deep, or an integer beyond 64 bits", path=path) from None


def with_options(config: RunConfig, **tables: dict[str, Any]) -> RunConfig:
    """``config`` with keys set from the command line, e.g.
    ``with_options(config, batch={"workers": 2})``, validated as a file is."""
    doc = dataclasses.asdict(config)
    for table, keys in tables.items():
        doc[table] = {**doc[table], **keys}
    return _validated(doc, None)


# -- the files made from the definition ------------------------------------------------

class _Schema(GenerateJsonSchema):
    def field_title_should_be_set(self, schema: Any) -> bool:
        return False  # the key is its own title; the description says the rest


def json_schema() -> dict:
    """The JSON Schema of a configuration file (``schemas/run_config.json``)."""
    doc = TypeAdapter(RunConfig).json_schema(schema_generator=_Schema)
    doc.pop("description", None)
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "name": "run_config", "version": SCHEMA_VERSION,
            **doc, "title": "rotcal run configuration (configs/defaults.toml and --config files)"}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return json.dumps(value) if isinstance(value, str) else repr(value)


def toml_text(config: RunConfig = RunConfig()) -> str:
    """``config`` as a TOML file, every key with its description
    (``configs/defaults.toml`` for the defaults)."""
    lines = ["# rotcal's run configuration: the defaults (written by `python -m rotcal.config`",
             "# from pipeline/rotcal/config.py; do not edit). A file given with --config overrides any",
             "# of these keys; unknown keys are refused."]
    for table in dataclasses.fields(RunConfig):
        section = getattr(config, table.name)
        about = " ".join((type(section).__doc__ or "").replace("``", "").split())
        lines += ["", f"[{table.name}]  # {about}"]
        rows = [(f"{name} = {_toml_value(getattr(section, name))}", info.description or "")
                for name, info in type(section).__pydantic_fields__.items()]
        width = max(len(key) for key, _ in rows)
        lines += [f"{key:<{width}}  # {description}" for key, description in rows]
    return "\n".join(lines) + "\n"


def generated_files() -> dict[str, str]:
    """The files made from this definition, by path in the checkout."""
    return {"schemas/run_config.json": json.dumps(json_schema(), indent=2) + "\n", "configs/defaults.toml": toml_text()}


def main(root: str = ".") -> None:
    """Write the generated files into the checkout at ``root``."""
    for name, text in generated_files().items():
        target = Path(root, name)
        if not target.parent.is_dir():
            sys.exit(f"{target.parent} is not a directory: run this in the rotcal checkout")
        target.write_text(text, encoding="utf-8")
        print(f"wrote {target}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
