"""Every Parquet table of two output directories compared column by column:
equal, or the largest difference of a numeric column as a fraction of the
column's largest value.

    python bench/compare_outputs.py OUT_A OUT_B
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import polars as pl


def compare(a: Path, b: Path) -> list[str]:
    lines = []
    for path in sorted(a.glob("*.parquet")):
        x, y = pl.read_parquet(path), pl.read_parquet(b / path.name)
        if x.equals(y):
            lines.append(f"{path.name}: equal")
            continue
        for column in x.columns:
            if x[column].equals(y[column]):
                continue
            if x[column].dtype.is_numeric():
                xv, yv = x[column].cast(pl.Float64).to_numpy(), y[column].cast(pl.Float64).to_numpy()
                scale = float(np.nanmax(np.abs(xv))) or 1.0
                lines.append(f"{path.name}.{column}: {np.nanmax(np.abs(xv - yv)) / scale:.2e} of the column's largest")
            else:
                lines.append(f"{path.name}.{column}: differs")
    return lines


if __name__ == "__main__":
    print("\n".join(compare(Path(sys.argv[1]), Path(sys.argv[2]))))
