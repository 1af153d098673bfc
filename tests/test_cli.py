"""Command-line habits: --version, -h, and tables printed whole when the
output is piped or logged (rich cut them to 80 columns: "paramet…")."""

import os
import subprocess
import sys

from rotcal import __version__


def test_version_and_short_help(cli):
    code, out, _ = cli("--version")
    assert (code, out.strip()) == (0, f"rotcal {__version__}")
    code, out, _ = cli("-h")
    assert code == 0 and "Usage:" in out and "[OPTIONS] COMMAND" in out and "batch" in out
    code, out, _ = cli("run", "-h")
    assert code == 0 and "run [OPTIONS]" in out


def test_piped_tables_are_not_cut(make_dataset, tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    run = subprocess.run([sys.executable, "-m", "rotcal", "run", str(make_dataset(3)), "--out", str(tmp_path / "out")],
                         capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr
    table = [line for line in run.stdout.splitlines() if line.startswith("│ s_u ")]
    assert table and "…" not in run.stdout
    # every rate's column is there: the default plan's DC and four rotation rates
    assert table[0].count("±") == 5
