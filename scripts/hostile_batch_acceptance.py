"""Issue 17's hostile batch acceptance (docs/fuzzing.md, docs/measured.md).

    python scripts/hostile_batch_acceptance.py [--root DIR] [--workers 2]

Builds a ROOT of 50 good simulated datasets and one dataset of each hostile
kind of issue 17, runs ``rotcal batch`` on it (the command, in a
subprocess) and checks every expectation of the acceptance item:

- the 50 good datasets published;
- ``glob/lot[1]`` beside ``glob/lot1`` published with its own data (its
  intrinsic table equals a run of the same files under a plain name, and
  differs from lot1's);
- a dataset with a copied capture published, with a ``duplicate_capture``
  finding in its time-base table;
- datasets named with a newline and with ESC published, their names escaped
  in the log (no raw control character in the output);
- 64 bogus message indexes published with the samples of the undamaged file
  (the index is not believed; nothing in the file is wrong but the index);
- every other hostile dataset quarantined with one line naming the file;
- exit status 4; and a rerun that processes nothing (exit 4 again: the
  quarantined datasets are still reported).

Prints the figures and exits 1 if any expectation fails. The batch runs
without the diagnosis (``[diagnosis] enabled = false``): the acceptance is
about what reaches the pipeline, and the diagnosis would only make the 50
good datasets slower.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import polars as pl
import zstandard
from mcap.writer import CompressionType, Writer

from rotcal.config import load_config
from rotcal.run import run_dataset
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz_inputs as fi  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SMALL = SimulationSpec(plan=Plan(step_samples=10, rates_hz=(0.5,), rotation_samples=200))
CONFIG = "[diagnosis]\nenabled = false\n"
GOOD = 50
NEWLINE, ESC = "forged\n2026-01-01T00:00:00.000Z rotcal batch: all ok", "esc\x1b[31mred"


def good(root: Path, rel: str, seed: int, fmt: str = "csv") -> Path:
    return write_dataset(simulate(SMALL, seed), SMALL, root / rel, fmt, device_id=f"dut-{seed}")


def copy(src: Path, dst: Path, toml: str | None = None) -> Path:
    shutil.copytree(src, dst)
    if toml is not None:
        (dst / "dataset.toml").write_text(toml)
    return dst


def set_cell(csv: Path, column: str, row: int, text: str) -> None:
    lines = csv.read_text().splitlines()
    k = lines[0].split(",").index(column)
    cells = lines[row].split(",")
    cells[k] = text
    lines[row] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")


def patch_mcap(path: Path, edit) -> None:
    """The MCAP at ``path`` with its first chunk's records edited (``edit(raw) -> raw, crc``)."""
    records = fi.mcap_records(path.read_bytes())
    k = next(i for i, (op, _) in enumerate(records) if op == fi.CHUNK)
    times, compression, raw = fi.open_chunk(records[k][1])
    new, crc = edit(raw)
    records[k] = (fi.CHUNK, fi.close_chunk(times, new, compression, crc))
    path.write_bytes(fi.mcap_bytes(records))


def first_message(raw: bytes) -> int:
    pos = 0
    for op, body in fi.mcap_records(raw, 0):
        if op == fi.MESSAGE:
            return pos
        pos += 9 + len(body)
    raise ValueError("no message")


def schema_capture(path: Path, name: str, text: str, data: bytes) -> None:
    with path.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start("", "hostile")
        channel = writer.register_channel("/imu", "cdr", writer.register_schema(name, "ros2msg", text.encode()))
        for k in range(3):
            writer.add_message(channel, k * 10**7, data, k * 10**7)
        writer.finish()


def mcap_of_chunks(*chunks: tuple[bytes, int]) -> bytes:
    """A file of zstd chunks (compressed data, declared size) and nothing else."""
    header = struct.pack("<I", 0) + struct.pack("<I", 7) + b"hostile"
    records = [(0x01, header)] + [(fi.CHUNK, struct.pack("<QQQI", 0, 0, size, 0) + struct.pack("<I", 4) + b"zstd"
                                   + struct.pack("<Q", len(data)) + data) for data, size in chunks]
    return fi.mcap_bytes(records + [(fi.DATA_END, struct.pack("<I", 0)), (fi.FOOTER, struct.pack("<QQI", 0, 0, 0))])


def build(root: Path) -> tuple[list[str], dict[str, str], list[str]]:
    """ROOT: the good datasets, the hostile ones expected published, and those
    expected quarantined with a needle of their reason."""
    goods = [f"lots/lot{k % 5}/dut{k:03d}" for k in range(GOOD)]
    for k, rel in enumerate(goods):
        good(root, rel, 1000 + k)
    template = root / "lots/lot0/dut000"
    mcap = good(root.parent / "templates", "mcap", 7, "mcap-cdr")
    published = ["glob/lot1", "glob/lot[1]", "copied", NEWLINE, ESC, "bogus_indexes"]
    good(root, "glob/lot1", 2001)
    good(root, "glob/lot[1]", 2002)
    copy(template, root / "copied")
    shutil.copyfile(sorted((root / "copied").glob("*.csv"))[1], root / "copied" / "zz_copy.csv")
    good(root, NEWLINE, 2003)
    good(root, ESC, 2004)
    copy(mcap, root / "bogus_indexes")
    capture = root / "bogus_indexes" / "capture.mcap"
    records = fi.mcap_records(capture.read_bytes())
    bogus = [(fi.MESSAGE_INDEX, struct.pack("<HI", 2, 0xFFFFFFF0))] * 64
    capture.write_bytes(fi.mcap_bytes(records[:2] + bogus + records[2:]))

    quarantined: dict[str, str] = {}

    def hostile(rel: str, needle: str, toml: str | None = None, src: Path = template) -> Path:
        quarantined[rel] = needle
        return copy(src, root / rel, toml)

    hostile("toml_nested", "nested more than", "x = " + "{a = " * 400 + "1" + "}" * 400 + "\n")
    hostile("toml_bigint", "64-bit", "[device]\nfull_scale = " + "9" * 5000 + "\n")
    hostile("toml_nul", "NUL", '[[capture]]\nfile = "00_x_static.csv\\u0000"\n')
    hostile("g_nan", "site.g_local", "[site]\ng_local = nan\n")
    hostile("g_u_nan", "site.g_local_uncertainty", "[site]\ng_local = 9.8\ng_local_uncertainty = nan\n")
    os.mkfifo(root / "trap.csv")
    quarantined["trap.csv"] = "not a regular file (a FIFO)"
    set_cell(sorted(hostile("angle_1e308", "1e308").glob("*_static.csv"))[0], "angle_deg", 5, "1e308")
    set_cell(sorted(hostile("u_1e308", "1e308").glob("*.csv"))[0], "u", 3, "1e308")
    set_cell(sorted(hostile("t_1e12", "beyond ±9e+09 s: time stamps in ms, us or ns?").glob("*.csv"))[0], "t", 3, "1e12")
    set_cell(sorted(hostile("non_utf8", "UTF-8").glob("*.csv"))[0], "u", 3, "x")
    bad = sorted((root / "non_utf8").glob("*.csv"))[0]
    bad.write_bytes(bad.read_bytes().replace(b",x,", b",\xff,"))
    set_cell(sorted(hostile("quote", "quote").glob("*.csv"))[0], "u", 3, '"12')
    glob_link = hostile("glob_capture", "'xz.csv' is a symbolic link pointing outside the dataset directory")
    shutil.copyfile(sorted(template.glob("*.csv"))[0], glob_link / "x[yz].csv")
    (glob_link / "xz.csv").symlink_to("/etc/passwd")
    whitespace = hostile("whitespace", "fewer columns",
                         '[format]\ndelimiter = "whitespace"\nheader = false\nnames = ["t", "u", "v", "w"]\n'
                         '[[capture]]\nfile = "blank.txt"\n')
    whitespace.joinpath("blank.txt").write_bytes(b" \t  \t \n" * (49 << 20 >> 3))
    long_message = hostile("mcap_long_message", "declares", src=mcap) / "capture.mcap"
    patch_mcap(long_message, lambda raw: (raw[: first_message(raw) + 1] + struct.pack("<Q", 1 << 62)
                                         + raw[first_message(raw) + 9 :], None))
    crc = hostile("mcap_crc", "CRC", src=mcap) / "capture.mcap"
    old_crc = struct.unpack_from("<I", fi.mcap_records(crc.read_bytes())[1][1], 24)[0]
    patch_mcap(crc, lambda raw: (raw[:-1] + bytes([raw[-1] ^ 0x40]), old_crc))
    huge = hostile("mcap_huge_record", "larger than the limit", src=mcap) / "capture.mcap"
    records = fi.mcap_records(huge.read_bytes())
    end = next(i for i, (op, _) in enumerate(records) if op == fi.DATA_END)  # a message record of 2^62 bytes before it
    huge.write_bytes(fi.MAGIC + fi.join_records(records[:end]) + b"\x05" + struct.pack("<Q", 1 << 62) + fi.join_records(records[end:]) + fi.MAGIC)
    string = root / "mcap_string_schema"
    string.mkdir()
    (string / "dataset.toml").write_text('[device]\nid = "string"\n')
    schema_capture(string / "capture.mcap", "std_msgs/msg/String", "string data", b"\x00\x01\x00\x00" + b"a" * (16 << 20))
    quarantined["mcap_string_schema"] = "std_msgs/msg/String"
    vector = root / "mcap_vector3_schema"
    vector.mkdir()
    (vector / "dataset.toml").write_text('[device]\nid = "vector3"\n')
    schema_capture(vector / "capture.mcap", "geometry_msgs/msg/Vector3", "float64 x\nfloat64 y\nfloat64 z", bytes(28))
    quarantined["mcap_vector3_schema"] = "geometry_msgs/msg/Vector3"
    zeros = zstandard.compress(bytes(256 << 20))
    (root / "mcap_chunk_bombs.mcap").write_bytes(mcap_of_chunks(*[(zeros, 256 << 20)] * 16))
    quarantined["mcap_chunk_bombs.mcap"] = "opcode 0"
    (root / "mcap_zero_chunks.mcap").write_bytes(mcap_of_chunks(*[(zstandard.compress(bytes(8 << 20)), 8 << 20)] * 3))
    quarantined["mcap_zero_chunks.mcap"] = "opcode 0"
    return goods, dict.fromkeys(published, ""), list(quarantined.items())


def batch(root: Path, out: Path, config: Path, workers: int) -> tuple[subprocess.CompletedProcess, float]:
    began = time.monotonic()
    run = subprocess.run([sys.executable, "-m", "rotcal", "batch", str(root), "--out", str(out), "--config", str(config),
                          "--workers", str(workers), "--json"], capture_output=True, text=True, cwd=REPO,
                         timeout=3600, env={**os.environ, "COLUMNS": "200"})
    return run, time.monotonic() - began


def rows(out: Path) -> dict[str, dict]:
    with sqlite3.connect(out / "manifest.sqlite") as db:
        db.row_factory = sqlite3.Row
        return {r["dataset_path"]: dict(r) for r in db.execute("SELECT * FROM batch_datasets")}


def table(out: Path, dataset_id: str, name: str) -> pl.DataFrame:
    return pl.read_parquet(out / "datasets" / dataset_id / f"{name}.parquet")


def main(argv: list[str] | None = None) -> int:
    import json

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=None, help="where ROOT and DIR are made (default: a temporary directory)")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    base = args.root or Path(tempfile.mkdtemp(prefix="rotcal-hostile-"))
    root, out, config = base / "root", base / "out", base / "batch.toml"
    for path in (root, out, base / "templates"):
        shutil.rmtree(path, ignore_errors=True)
    base.mkdir(parents=True, exist_ok=True)
    config.write_text(CONFIG)
    began = time.monotonic()
    goods, published, quarantined = build(root)
    print(f"ROOT {root}: {GOOD} good datasets, {len(published)} hostile ones expected published, "
          f"{len(quarantined)} expected quarantined; built in {time.monotonic() - began:.0f} s")
    first, first_s = batch(root, out, config, args.workers)
    second, second_s = batch(root, out, config, args.workers)
    checks: list[tuple[str, bool]] = []
    summary = json.loads(first.stdout) if first.stdout.startswith("{") else {}
    again = json.loads(second.stdout) if second.stdout.startswith("{") else {}
    manifest = rows(out) if (out / "manifest.sqlite").exists() else {}
    status = {path: row["status"] for path, row in manifest.items()}
    reasons = {p["dataset_path"]: p["reason"] for p in summary.get("problems", [])}
    checks.append((f"the {GOOD} good datasets published", all(status.get(g) == "ok" for g in goods)))
    checks.append(("the hostile datasets expected published are", all(status.get(p) == "ok" for p in published)))
    ids = {path: row["dataset_id"] for path, row in manifest.items()}
    if status.get("glob/lot[1]") == "ok" and status.get("glob/lot1") == "ok":
        plain = base / "plain"
        shutil.rmtree(plain, ignore_errors=True)
        shutil.copytree(root / "glob/lot[1]", plain / "lot_1")
        run_dataset(plain / "lot_1", plain / "out", None, load_config(config))
        numbers = pl.selectors.float()
        own = table(out, ids["glob/lot[1]"], "intrinsic").select(numbers)
        checks.append(("lot[1] published with its own data", own.equals(pl.read_parquet(plain / "out/intrinsic.parquet").select(numbers))
                       and not own.equals(table(out, ids["glob/lot1"], "intrinsic").select(numbers))))
    if status.get("copied") == "ok":
        found = table(out, ids["copied"], "timebase").filter(pl.col("check") == "duplicate_capture")
        checks.append(("copied capture: one duplicate_capture finding", found.select("capture", "detected").rows() == [("zz_copy.csv", True)]))
    log = first.stderr
    checks.append(("names escaped in the log", "\x1b" not in log + first.stdout and "forged\\n2026" in log and "esc\\x1b[31mred" in log
                   and not any(line.startswith("2026-01-01T00:00:00.000Z") for line in log.splitlines())))
    if status.get("bogus_indexes") == "ok":  # the same tables as the undamaged file's
        undamaged = base / "plain" / "mcap"
        run_dataset(base / "templates" / "mcap", undamaged, None, load_config(config))
        checks.append(("bogus message indexes: the undamaged file's results", all(
            table(out, ids["bogus_indexes"], name).drop("dataset").equals(pl.read_parquet(undamaged / f"{name}.parquet").drop("dataset"))
            for name in ("segments", "fits", "intrinsic"))))
    wrong = [(rel, reasons.get(rel, status.get(rel))) for rel, needle in quarantined
             if status.get(rel) != "quarantined" or needle not in reasons.get(rel, "") or "\n" in reasons.get(rel, "")
             or not reasons.get(rel, "").startswith(str(root))]
    checks.append((f"the {len(quarantined)} other hostile datasets quarantined with one line naming the file", not wrong))
    checks.append(("exit status 4", first.returncode == 4))
    checks.append(("a rerun processes nothing", again.get("processed") == 0 and second.returncode == 4
                   and again.get("unchanged") == summary.get("discovered")))
    print(f"first run: exit {first.returncode}, {summary.get('discovered')} datasets: {summary.get('ok')} ok, "
          f"{summary.get('quarantined')} quarantined, {summary.get('errors')} errors; {first_s:.0f} s wall")
    print(f"rerun: exit {second.returncode}, processed {again.get('processed')}, unchanged {again.get('unchanged')} "
          f"(still quarantined {again.get('still_quarantined')}); {second_s:.1f} s wall")
    for rel, _ in quarantined:
        print(f"  quarantined {rel!r}: {reasons.get(rel, status.get(rel))}")
    for rel, got in wrong:
        print(f"  UNEXPECTED {rel!r}: {got}")
    for name, ok in checks:
        print(f"{'PASS' if ok else 'FAIL'}  {name}")
    if first.returncode not in (0, 4) or not all(ok for _, ok in checks):
        print(first.stderr[-3000:])
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
