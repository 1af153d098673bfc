"""What the certificate costs a run: its content (tables read, figures
drawn), the HTML page and the PDF (Typst) drawn from it, for each of
several run directories in one process, after one warm-up compile (typst
imported, its fonts read). Each certificate is compiled once: Typst
memoises layout within a process, so compiling the same certificate again
costs a tenth and would flatter it.

    python bench/certificate_pdf.py RUN_DIR [RUN_DIR ...] [--no-figures]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import typst

from rotcal.report.certificate import document, html
from rotcal.report.certificate_pdf import pdf_bytes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--no-figures", action="store_true", help="as rotcal batch draws it (no --figures)")
    args = parser.parse_args()
    start = time.perf_counter()
    typst.compile(b"#set document(date: none)\nwarm-up", ignore_system_fonts=True)
    print(f"typst's first compile in this process: {time.perf_counter() - start:.3f} s")
    times: dict[str, list[float]] = {"content": [], "html": [], "pdf": []}
    for run_dir in args.run_dirs:
        start = time.perf_counter()
        doc = document(run_dir, figures=not args.no_figures)
        built = time.perf_counter()
        html(doc)
        paged = time.perf_counter()
        pages = pdf_bytes(doc)
        times["content"].append(built - start)
        times["html"].append(paged - built)
        times["pdf"].append(time.perf_counter() - paged)
        print(f"{run_dir}: content {times['content'][-1]:.3f} s, html {times['html'][-1]:.3f} s, "
              f"pdf {times['pdf'][-1]:.3f} s ({len(pages):,} bytes)")
    print("medians: " + ", ".join(f"{name} {statistics.median(v):.3f} s" for name, v in times.items()))


if __name__ == "__main__":
    main()
