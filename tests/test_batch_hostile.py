"""Hostile inputs under ROOT: MCAP records and chunks claiming (or expanding
to) absurd sizes, a CSV with a 256 MB line, an oversized dataset.toml, and
every way of pointing outside a dataset (``..``, absolute paths, file and
directory links). Each is refused with its one-line reason, in bounded
memory (measured in a subprocess), while a good dataset beside them is
processed; nothing outside ROOT and DIR is opened and nothing is unpickled."""

import json
import os
import shutil
import struct
import subprocess
import sys

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import Chunk, Header

from rotcal.simulate import simulate, write_dataset

from batch_support import NO_DIAGNOSIS, REPO, SMALL, make_root

MAGIC = b"\x89MCAP0\r\n"
LIMIT = 1 << 20  # the test's limits: 1 MiB lines, records, chunks and dataset.toml
HUGE = 256 << 20

# Runs a warm-up batch (so that libraries' first-use memory is not counted),
# then the hostile batch; reports the peak RSS growth, every file opened or
# directory listed outside ROOT and DIR, and every unpickling or process start.
SCRIPT = """
import json, os, resource, sys
from pathlib import Path
warm, root, out, config, outside = sys.argv[1:6]
seen = []
def hook(event, args):
    if event in ("open", "os.listdir", "os.scandir") and args and isinstance(args[0], (str, bytes, os.PathLike)):
        if os.fsdecode(args[0]).startswith(outside):
            seen.append(f"{event} {os.fsdecode(args[0])}")
    elif event in ("pickle.find_class", "subprocess.Popen", "os.system", "os.exec", "os.posix_spawn"):
        seen.append(f"{event} {args!r}")
from rotcal.batch.runner import run_batch
from rotcal.config import load_config
cfg = load_config(Path(config))
run_batch(Path(warm), Path(out) / "warm", cfg)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
sys.addaudithook(hook)
summary = run_batch(Path(root), Path(out) / "batch", cfg)
growth = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base
print(json.dumps({"summary": summary.as_dict(), "growth_kib": growth, "seen": seen}))
"""


def mcap_bytes(*records) -> bytes:
    builder = RecordBuilder()
    Header(profile="", library="hostile").write(builder)
    for record in records:
        record.write(builder)
    return MAGIC + builder.end()


def zstd_zeros(size: int) -> bytes:
    """``size`` zero bytes, zstd-compressed, without holding them in memory."""
    compressor = zstandard.ZstdCompressor().compressobj()
    block = bytes(1 << 20)
    return b"".join(compressor.compress(block) for _ in range(size >> 20)) + compressor.flush()


def sparse(path, head: bytes, size: int) -> None:
    with path.open("wb") as fh:
        fh.write(head)
        fh.truncate(size)


def test_hostile_inputs_are_refused_in_bounded_memory(tmp_path):
    root, warm, out, outside = tmp_path / "root", tmp_path / "warm", tmp_path / "out", tmp_path / "outside"
    make_root(warm, [9])
    make_root(root, [1])  # lot1/dut001: a good dataset among the hostile ones
    good = write_dataset(simulate(SMALL, 2), SMALL, outside / "ds")  # valid: reading it would succeed
    secret = sorted(good.glob("*.csv"))[0]

    def dataset(name: str, toml: str = "") -> os.PathLike:
        path = root / name
        shutil.copytree(good, path)
        (path / "dataset.toml").write_text(toml)
        return path

    # Paths outside the dataset, every way.
    dataset("dotdot", f'[[capture]]\nfile = "../../outside/ds/{secret.name}"\n')
    dataset("absolute", f'[[capture]]\nfile = "{secret}"\n')
    (dataset("capture_link", '[[capture]]\nfile = "link.csv"\n') / "link.csv").symlink_to(secret)
    (dataset("auto_link") / "zz_leak.csv").symlink_to(secret)
    toml_link = dataset("toml_link") / "dataset.toml"
    toml_link.unlink()
    toml_link.symlink_to(good / "dataset.toml")
    (root / "dir_link").symlink_to(good)
    (root / "file_link.csv").symlink_to(secret)
    # Sizes: a dataset.toml, a CSV line, MCAP records and chunks.
    sparse(dataset("big_toml") / "dataset.toml", b"[device]\n", HUGE)
    sparse(root / "long_line.csv", b"t,u,v,w\n", HUGE)
    (root / "huge_record.mcap").write_bytes(mcap_bytes() + b"\x05" + struct.pack("<Q", 1 << 62))
    bomb = zstd_zeros(HUGE)
    (root / "chunk_bomb.mcap").write_bytes(mcap_bytes(Chunk("zstd", bomb, 0, 0, 0, HUGE)))
    (root / "chunk_liar.mcap").write_bytes(mcap_bytes(Chunk("zstd", bomb, 0, 0, 0, LIMIT // 2)))
    (root / "chunk_absurd.mcap").write_bytes(mcap_bytes(Chunk("zstd", bomb, 0, 0, 0, 1 << 60)))
    config = tmp_path / "limits.toml"
    config.write_text(NO_DIAGNOSIS + f"[limits]\nmax_line_bytes = {LIMIT}\nmax_mcap_record_bytes = {LIMIT}\n"
                      f"max_dataset_toml_bytes = {LIMIT}\n[batch]\nworkers = 1\n")

    run = subprocess.run([sys.executable, "-c", SCRIPT, warm, root, out, config, str(outside)],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    summary = report["summary"]
    reasons = {p["dataset_path"]: p["reason"] for p in summary["problems"]}
    expected = {
        "dotdot": "file '../../outside/ds/" + secret.name + "' points outside the dataset directory",
        "absolute": f"file '{secret}' points outside the dataset directory",
        "capture_link": "file 'link.csv' points outside the dataset directory",
        "auto_link": "'zz_leak.csv' is a symbolic link pointing outside the dataset directory",
        "toml_link": "'dataset.toml' is a symbolic link pointing outside the dataset directory",
        "dir_link": "a symbolic link to a directory: rotcal batch does not follow directory links",
        "file_link.csv": "'file_link.csv' is a symbolic link pointing outside the dataset directory",
        "big_toml": f"dataset.toml is larger than the limit of {LIMIT} bytes",
        "long_line.csv": f"a line is longer than the limit of {LIMIT} bytes",
        "huge_record.mcap": f"an MCAP record is larger than the limit of {LIMIT} bytes",
        "chunk_bomb.mcap": f"an MCAP chunk expands to {HUGE} bytes, above the limit of {LIMIT} bytes",
        "chunk_liar.mcap": f"corrupt MCAP: a chunk holds {LIMIT // 2 + 1} bytes where it declares {LIMIT // 2}",
        "chunk_absurd.mcap": f"an MCAP chunk expands to {1 << 60} bytes, above the limit of {LIMIT} bytes",
    }
    assert set(reasons) == set(expected)
    for name, needle in expected.items():
        assert needle in reasons[name] and "\n" not in reasons[name], (name, reasons[name])
        assert reasons[name].startswith(str(root)), reasons[name]  # names the file
    assert (summary["ok"], summary["quarantined"], summary["errors"], summary["exit_status"]) == (1, 13, 0, 4)
    assert report["seen"] == []
    assert report["growth_kib"] < 48 * 1024, report["growth_kib"]  # the hostile files are 256 MB and more
