"""The ``rotcal`` command line: resolves options once and calls one library
function per command. Domain errors become a one-line message and an exit
status here, and nowhere else. Each command imports the stages it calls
inside its body: `rotcal --help` and a batch's main process then load no
scipy (0.29 s to import this module, against 0.77 s with the imports at the
top)."""

from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from rich.console import Console
from rich.markup import escape
from typer import _click as click
from typer.core import TyperCommand, TyperGroup

from rotcal.config import load_config, with_options
from rotcal.errors import ExitCode, RotcalError, printable

if TYPE_CHECKING:
    from rotcal.report.publish import OutputDir
    from rotcal.simulate import SimulationSpec

class _Command(TyperCommand):
    """A command's help as users of other command lines expect it: the usage
    line names its arguments (``rotcal run [OPTIONS] DATASET``, not typer's
    ``{dataset}``), and a flag shows no ``<bool>`` value it does not take."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        for param in self.params:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = ""

    def get_help_option(self, ctx):
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option

    def collect_usage_pieces(self, ctx) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for param in self.get_params(ctx):
            if param.param_type_name == "argument":
                name = param.metavar or param.name.upper()
                pieces.append(name if param.required else f"[{name}]")
        return pieces


class _Group(TyperGroup):
    def get_help_option(self, ctx):
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option


app = typer.Typer(cls=_Group, add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  context_settings={"help_option_names": ["-h", "--help"]},
                  help="Rotation-table calibration of three-axis accelerometers.")
# Piped or logged output has no terminal width to honour: tables are printed
# whole (rich would cut them to 80 columns: "paramet…"); a user's COLUMNS wins.
# Emoji off: rich would show a ":x:" in a message or a file name as an emoji.
_UNBOUNDED = 1000
out = Console(emoji=False, width=None if sys.stdout.isatty() or "COLUMNS" in os.environ else _UNBOUNDED)
err = Console(stderr=True, emoji=False, width=None if sys.stderr.isatty() or "COLUMNS" in os.environ else _UNBOUNDED)


def _version(value: bool) -> None:
    if value:
        from rotcal import __version__

        out.print(f"rotcal {__version__}", highlight=False, markup=False)
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, metavar="", help="print rotcal's version and exit")] = False,
) -> None:
    """Rotation-table calibration of three-axis accelerometers."""

# choices the CLI checks and its help lists (the simulator and the exporter check them again for the API)
SimulatedFormat = Literal["csv", "csv-unlabelled", "mcap-cdr", "mcap-json"]
ExportFormat = Literal["ardupilot", "px4", "yaml", "json"]
EFFECT = "NAME:KEY=VALUE,..."


SITE_HELP = r"the laboratory's site file (its \[laboratory], \[equipment], \[certificate] fields for the certificate); default: site.toml beside the dataset (rotcal batch: in ROOT)"
REPLACE_HELP = "replace files in the output directory that no rotcal listing (rotcal-files.json) names"


def _out_dir(path: Path, replace: bool = False, inputs: tuple[Path | None, ...] = (), listed: bool = True) -> OutputDir:
    """The output directory checked before any work (``report.publish.check_out``),
    so that a run never ends in an error after its computation."""
    from rotcal.report.publish import OutputDir, check_out

    return check_out(OutputDir(path, replace), inputs, listed)


def _writable(path: Path) -> Path:
    """A directory written into, not replaced (``rotcal intrinsic``, ``rotcal batch``), checked before any work."""
    from rotcal.report.publish import usable

    usable(path, swapped=False)
    return path


def _print_diagnosis(diagnosis) -> None:
    from rotcal.report import findings_table

    found = int(diagnosis.findings["detected"].sum())
    if not found:
        out.print("diagnosis: no finding; the recording agrees with the papers' model within its noise")
        return
    out.print(findings_table(diagnosis.findings, f"diagnosis: {found} finding{'s' if found > 1 else ''}"))


def _print_outcome(outcome, quiet: bool = False) -> None:
    # the stages and their tables load when a command needs them: rotcal batch's start-up stays short
    from rotcal.model.calibration import BASELINE
    from rotcal.report import pose_check_table, recommendation_line, static_fit_summary, summary_table

    for note in outcome.notes:
        err.print(f"[yellow]note:[/] {escape(note)}", highlight=False)
    for warning in outcome.warnings:
        err.print(f"[yellow]warning:[/] {escape(warning)}", highlight=False)
    if not quiet:
        unit = escape(outcome.output_unit)  # dataset.toml's text, printed inside the table's rich markup
        chosen = outcome.recommended  # the results calibration.json holds: the table shows them, not the baseline's
        out.print(summary_table(chosen.results, unit, f"{outcome.dataset}: intrinsic parameters of the recommended model "
                                                      f"({chosen.model}), value ± U (95 %)"))
        out.print(recommendation_line(chosen), highlight=False, markup=False)
        # a static recording whose poses do not determine the nine parameters has no baseline rows
        if chosen.model != BASELINE and (outcome.static is None or outcome.static.model == BASELINE):
            out.print(f"the baseline model's parameters are beside them in intrinsic.parquet (model = {BASELINE})",
                      highlight=False, markup=False)
        if outcome.diagnosis is not None:
            _print_diagnosis(outcome.diagnosis)
        if outcome.static is not None:
            out.print(static_fit_summary(outcome.static, unit), highlight=False)
            out.print(pose_check_table(outcome.static.check, outcome.static.result.g_local,
                                       f"{escape(outcome.dataset)}: |a| check, g_local = {outcome.static.result.g_local:g} m/s^2"))
    folder = outcome.written[0].parent if outcome.written else None
    out.print(f"tables written to {folder}: {', '.join(p.name for p in outcome.written)}", highlight=False, markup=False)


@app.command(cls=_Command)
def run(
    dataset: Annotated[Path, typer.Argument(metavar="DATASET", help="dataset directory or single capture file")],
    out_dir: Annotated[Path, typer.Option("--out", metavar="DIR", help="directory for the result tables")],
    meta: Annotated[Path | None, typer.Option(metavar="FILE", help="dataset.toml kept outside the dataset")] = None,
    config: Annotated[Path | None, typer.Option(metavar="FILE", help="run configuration overriding configs/defaults.toml")] = None,
    workers: Annotated[int | None, typer.Option(min=0, metavar="N", help=r"cores the run uses (\[run] workers); 0 = every core it may run on")] = None,
    quiet: Annotated[bool, typer.Option(help="do not print the summary table")] = False,
    json_summary: Annotated[bool, typer.Option("--json", help="print the run's summary (the recommended result per rate, warnings, files written) as JSON on stdout")] = False,
    replace_files: Annotated[bool, typer.Option("--replace", help=REPLACE_HELP)] = False,
    site: Annotated[Path | None, typer.Option(metavar="FILE", help=SITE_HELP)] = None,
) -> None:
    """Run the whole pipeline on one dataset."""
    target = _out_dir(out_dir, replace_files, (dataset, meta, config))
    from rotcal.run import run_dataset

    cfg = load_config(config)
    if workers is not None:
        cfg = with_options(cfg, run={"workers": workers})
    if site is not None:
        cfg = with_options(cfg, report={"site": str(site.resolve())})
    if not json_summary:
        _print_outcome(run_dataset(dataset, target, meta, cfg), quiet)
        return
    from rotcal.report import run_summary

    try:
        outcome = run_dataset(dataset, target, meta, cfg)
    except RotcalError as exc:  # the document says why; the one-line message follows on stderr
        _print_json({"dataset": str(dataset), "exit_status": int(exc.exit_code), "error": str(exc)})
        raise
    _print_json(run_summary(outcome.dataset, outcome.output_unit, outcome.recommended, outcome.warnings,
                            outcome.notes, outcome.written))


def _print_json(document: dict) -> None:
    """A command's ``--json`` document on stdout (``run``, ``batch``)."""
    import json

    print(json.dumps(document, indent=2))


def _spec(config: Path | None, effect: list[str] | None) -> SimulationSpec:
    from rotcal.simulate import SimulationSpec, spec_from_toml

    spec = spec_from_toml(config) if config else SimulationSpec()
    return spec.with_effects(*(effect or ()))


@app.command(name="simulate", cls=_Command)
def simulate_cmd(
    directory: Annotated[Path, typer.Argument(metavar="DIR", help="where to write the dataset")],
    seed: Annotated[int, typer.Option(help="random seed; the same seed gives the same files")] = 1,
    fmt: Annotated[SimulatedFormat, typer.Option("--format", help="the captures' form")] = "csv",
    effect: Annotated[list[str] | None, typer.Option(metavar=EFFECT, help="an effect switched on (repeatable), e.g. centripetal:axis=x,radius_m=0.22")] = None,
    # rich reads [name] in help text as markup: the backslashes keep the table names
    config: Annotated[Path | None, typer.Option(metavar="FILE", help=r"simulation TOML: tables \[plan], \[dut], \[site], \[timebase], \[noise], \[\[effect]]")] = None,
    continuous: Annotated[bool, typer.Option(help="one recording with the transitions between segments (ramps, step moves, rests, hand reorientation)")] = False,
    timebase: Annotated[str | None, typer.Option(metavar="KEY=VALUE,...", help="logger defects key=value,..., e.g. drop_fraction=0.01,jitter_s=0.005,clock_drift_ppm=200")] = None,
    plan: Annotated[str | None, typer.Option(metavar="KEY=VALUE,...", help="plan numbers key=value,..., e.g. step_move_s=0,dt_s=0.05 (steps faster than a sample)")] = None,
    noise: Annotated[str | None, typer.Option(metavar="KEY=VALUE,...", help="the DUT's noise key=value,... (docs/noise.md), e.g. white_sd=6,ar=0.5,ar_sd=4,gauss_markov=100:2, or preset=adxl345; default: white, dut noise_std")] = None,
    replace_files: Annotated[bool, typer.Option("--replace", help="replace DIR's contents; without it a DIR that is not empty is refused")] = False,
) -> None:
    """Write a synthetic dataset (default: the Gaitan & Geist 2021 test plan)."""
    target = _out_dir(directory, replace_files, listed=False)
    spec = _spec(config, effect)
    if continuous:
        spec = replace(spec, plan=replace(spec.plan, continuous=True))
    if timebase:
        spec = spec.with_timebase(timebase)
    if plan:
        spec = spec.with_plan(plan)
    if noise:
        spec = spec.with_noise(noise)
    from rotcal.report.publish import publish_directory
    from rotcal.simulate import simulate, write_dataset
    from rotcal.simulate.blocks import streamable, write_streamed

    if streamable(spec, fmt):  # the same bytes, generated and written a block at a time: any length
        def write(staging: Path) -> list[Path]:
            return [write_streamed(spec, seed, staging, target.path.name)]
    else:
        sim = simulate(spec, seed)

        def write(staging: Path) -> list[Path]:
            return [write_dataset(sim, spec, staging, fmt, target.path.name)]
    # no listing: a dataset is the user's once written, so any file in DIR is refused without --replace
    publish_directory(target, write, listed=False)
    out.print(f"dataset written to {directory} (truth in {directory / 'truth.json'})", highlight=False, markup=False)


@app.command(cls=_Command)
def demo(
    directory: Annotated[Path, typer.Option("--dir", metavar="DIR", help="where the demo writes data and results")] = Path("rotcal-demo"),
    seed: Annotated[int, typer.Option(help="random seed of the simulated DUT")] = 1,
    effect: Annotated[list[str] | None, typer.Option(metavar=EFFECT, help="an effect switched on (repeatable), e.g. centripetal:axis=y,radius_m=0.22")] = None,
    replace_files: Annotated[bool, typer.Option("--replace", help=REPLACE_HELP)] = False,
) -> None:
    """Simulate a default dataset and run the pipeline on it, in DIR (replaced whole: data/, results/)."""
    target = _out_dir(directory, replace_files)
    spec = _spec(None, effect)
    from rotcal.report.publish import publish_directory
    from rotcal.run import run_dataset
    from rotcal.simulate import simulate, write_dataset

    config = with_options(load_config(None), uncertainty={"monte_carlo": True})  # the demo shows every table
    outcomes = []

    def write(staging: Path) -> list[Path]:  # the dataset and its results, published as one folder
        data = write_dataset(simulate(spec, seed), spec, staging / "data", "csv")
        out.print(f"simulated dataset in {directory / 'data'}", highlight=False, markup=False)
        outcomes.append(run_dataset(data, staging / "results", None, config))
        return list(outcomes[0].written)

    published = publish_directory(target, write)  # the run's files where they now are, then the demo's listing
    _print_outcome(replace(outcomes[0], written=published[:-1]))


@app.command(cls=_Command)
def intrinsic(
    matrix: Annotated[Path, typer.Option(metavar="FILE", help="CSV of P: rows x, y, z, columns u, v, w, optionally 3 rows of standard uncertainties")],
    out_dir: Annotated[Path, typer.Option("--out", metavar="DIR", help="directory for FILESTEM_intrinsic.parquet")] = Path("."),
    unit: Annotated[str, typer.Option(metavar="UNIT", help="the DUT's output unit (P is in m/s^2 per output unit)")] = "output unit",
) -> None:
    """Intrinsic sensitivities and angles of a cross-sensitivity matrix another lab reports."""
    from rotcal.metrology import matrix_intrinsic
    from rotcal.report import matrix_table

    frame, path = matrix_intrinsic(matrix, _writable(out_dir), unit)
    out.print(matrix_table(frame, f"{escape(matrix.name)}: intrinsic parameters, standard uncertainty"))
    out.print(f"written to {path}", highlight=False, markup=False)


@app.command(name="apply", cls=_Command)
def apply_cmd(
    calibration: Annotated[Path, typer.Argument(metavar="CALIBRATION", help="calibration.json, or a run's output directory holding one")],
    recording: Annotated[Path, typer.Argument(metavar="RECORDING", help="dataset directory or single capture file to calibrate")],
    out_file: Annotated[Path, typer.Option("--out", metavar="FILE", help="output file: .parquet, .csv or .mcap (sensor_msgs/msg/Imu)")],
    rate: Annotated[float | None, typer.Option(metavar="HZ", help="the calibration's rate (Hz) to apply; default DC")] = None,
    uncertainty: Annotated[bool, typer.Option("--uncertainty", help="each sample's standard uncertainty from the calibration's covariance")] = False,
    meta: Annotated[Path | None, typer.Option(metavar="FILE", help="the recording's dataset.toml kept outside it")] = None,
) -> None:
    """Calibrate a recording: a = P (R - O) in m/s^2 in the calibration's frame (documentation: Using a calibration)."""
    from rotcal.apply import apply_calibration

    done = apply_calibration(calibration, recording, out_file, rate, uncertainty, meta)
    for note in done.notes:
        err.print(f"[yellow]note:[/] {escape(note)}", highlight=False)
    out.print(f"{done.samples:,} samples calibrated ({done.rate_hz:g} Hz, frame {done.frame}) to {done.path}",
              highlight=False, markup=False)


@app.command(name="export", cls=_Command)
def export_cmd(
    calibration: Annotated[Path, typer.Argument(metavar="CALIBRATION", help="calibration.json, or a run's output directory holding one")],
    fmt: Annotated[ExportFormat, typer.Option("--format", help="a flight stack's parameters, imu_tk's T, K, B (yaml) or plain json")],
    rate: Annotated[float | None, typer.Option(metavar="HZ", help="the calibration's rate (Hz) to export; default DC")] = None,
    out_file: Annotated[Path | None, typer.Option("--out", metavar="FILE", help="file to write; default standard output")] = None,
    nominal_scale: Annotated[float | None, typer.Option(metavar="SCALE", help="ardupilot, px4: the driver's m/s^2 per output unit (needed unless the unit is m/s^2)")] = None,
) -> None:
    """Write the calibration in a flight stack's or IMU tool's form (documentation: Using a calibration)."""
    from rotcal.apply import export_calibration, writable_file
    from rotcal.model.calibration import Calibration

    target = None if out_file is None else writable_file(out_file)
    result = export_calibration(Calibration.read(calibration), fmt, rate, nominal_scale)
    for warning in result.warnings:
        err.print(f"[yellow]warning:[/] {escape(warning)}", highlight=False)
    if target is None:
        sys.stdout.write(result.text)
    else:
        out.print(f"{result.format} export written to {result.write(target)}", highlight=False, markup=False)

@app.command(cls=_Command)
def certificate(
    run_dir: Annotated[Path, typer.Argument(metavar="RUN_DIR", help="a run's output directory (calibration.json and its tables)")],
) -> None:
    """Render a run's calibration certificate (RUN_DIR/certificate.html and .pdf) again from its published files."""
    from rotcal.report.certificate import rewrite_certificates

    written = rewrite_certificates(_writable(run_dir))
    out.print(f"certificate written to {', '.join(str(p) for p in written)}", highlight=False, markup=False)


def main() -> None:
    """Console entry point: a user's error exits with a one-line message."""
    try:
        # not standalone: the command line's own errors (a missing option, a
        # value not among the choices) come here too, for the one message style
        status = app(prog_name="rotcal", standalone_mode=False)
    except RotcalError as exc:
        _fail(str(exc), exc.exit_code)  # errors.ExitCode, the one table of exit statuses
    except click.exceptions.NoArgsIsHelpError as exc:  # `rotcal`, `rotcal run` alone: the help, as typer prints it
        out.print(exc.ctx.get_help() if exc.ctx else "", highlight=False, markup=False)
        sys.exit(ExitCode.BAD_INPUT)
    except click.exceptions.UsageError as exc:
        command = exc.ctx.command_path if exc.ctx else "rotcal"
        message = exc.format_message().replace(": Value error, ", ": ").rstrip(".")
        _fail(f"{message}; see '{command} -h'", ExitCode.BAD_INPUT)
    except typer.Abort:  # end of input at a prompt
        sys.exit(130)
    sys.exit(status if isinstance(status, int) else 0)


def _fail(message: str, status: int) -> None:
    # markup off: messages quote dataset.toml tables ([format], [plan]) and paths as they are
    # control characters in a path must not reach the terminal (errors.printable)
    err.print(f"rotcal: error: {printable(message)}", highlight=False, markup=False, soft_wrap=True)
    sys.exit(status)


@app.command(cls=_Command)
def batch(
    root: Annotated[Path, typer.Argument(metavar="ROOT", help="folder searched for datasets: directories holding dataset.toml, and single capture files")],
    out_dir: Annotated[Path, typer.Option("--out", metavar="DIR", help="output directory: per-dataset tables, combined dataset, manifest")],
    config: Annotated[Path | None, typer.Option(metavar="FILE", help="run configuration overriding configs/defaults.toml; its batch table may set workers and executor")] = None,
    workers: Annotated[int | None, typer.Option(min=0, metavar="N", help="cores in all, shared by the datasets processed at once on the local pool; 0 = every core it may run on")] = None,
    executor: Annotated[str | None, typer.Option(metavar="local|dask://HOST:PORT", help="local, or dask://HOST:PORT to run on an existing Dask scheduler")] = None,
    json_summary: Annotated[bool, typer.Option("--json", help="print the run's summary as JSON on stdout")] = False,
    figures: Annotated[bool, typer.Option(help=r"draw each dataset's PNG figures too (\[report] figures); off, a batch writes the tables and report.md")] = False,
    pdf: Annotated[bool, typer.Option(help=r"write each dataset's certificate.pdf too (\[report] pdf; about 0.5 s a dataset); off, a batch writes certificate.html")] = False,
    site: Annotated[Path | None, typer.Option(metavar="FILE", help=SITE_HELP)] = None,
) -> None:
    """Process every new or changed dataset under ROOT: incremental, crash-safe, for schedulers (documentation: Batch runs)."""
    from rotcal.batch import Reporter, run_batch

    options = {"workers": workers, "executor": executor}
    report = {"figures": figures, "pdf": pdf, **({"site": str(site.resolve())} if site is not None else {})}
    cfg = with_options(load_config(config), batch={k: v for k, v in options.items() if v is not None}, report=report)
    with Reporter(err) as reporter:
        summary = run_batch(root, _writable(out_dir), cfg, reporter)
    if json_summary:
        _print_json(summary.as_dict())
    else:
        out.print(summary.text(), highlight=False, markup=False, soft_wrap=True)
    raise typer.Exit(summary.exit_status)
