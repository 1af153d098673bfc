"""What the certificate costs a run: its content (tables read, the |a|
figure drawn), the HTML page and the PDF (Typst) drawn from it, medians of
``--repeats`` on a run's output directory; and, in a new process, importing
typst with its first compile.

    python bench/certificate_pdf.py RUN_DIR [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rotcal.report.certificate import document, html
from rotcal.report.certificate_pdf import pdf_bytes

FIRST = ("import time; start = time.perf_counter(); import typst; "
         "typst.compile(b'#set document(date: none)\\nx', ignore_system_fonts=True); print(time.perf_counter() - start)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    pdf_bytes(document(args.run_dir))  # typst loaded and its fonts read once, as a run's first certificate does
    times: dict[str, list[float]] = {"content": [], "html": [], "pdf": []}
    for _ in range(args.repeats):
        start = time.perf_counter()
        doc = document(args.run_dir)
        built = time.perf_counter()
        html(doc)
        paged = time.perf_counter()
        pages = pdf_bytes(doc)
        times["content"].append(built - start)
        times["html"].append(paged - built)
        times["pdf"].append(time.perf_counter() - paged)
    for name, values in times.items():
        print(f"{name:8s} {statistics.median(values):.3f} s")
    first = subprocess.run([sys.executable, "-c", FIRST], capture_output=True, text=True, check=True)
    print(f"typst import and first compile, new process: {float(first.stdout):.3f} s; PDF {len(pages):,} bytes")


if __name__ == "__main__":
    main()
