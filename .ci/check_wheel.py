"""Does the wheel hold exactly what the checkout ships? Every module under
pipeline/rotcal/ as rotcal/..., the schemas as rotcal_schemas/ and the configs as
rotcal_configs/; nothing missing (issue 12: a subpackage left out broke
every installed `rotcal demo`) and nothing stale.

    python .ci/check_wheel.py DIST/rotcal-*.whl
"""

from __future__ import annotations

import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# installed package -> (folder in the checkout, the files it ships)
SHIPPED = {"rotcal": ("pipeline/rotcal", ["*.py", "*.html", "*.typ"]), "rotcal_schemas": ("schemas", ["*.py", "*.json"]),
           "rotcal_configs": ("configs", ["*.py", "*.toml"])}


def expected() -> set[str]:
    names = set()
    for package, (folder, patterns) in SHIPPED.items():
        root = REPO / folder
        names |= {f"{package}/{path.relative_to(root).as_posix()}" for pattern in patterns for path in root.rglob(pattern)}
    return names


def main(wheel: str) -> int:
    with zipfile.ZipFile(wheel) as archive:
        held = {name for name in archive.namelist() if ".dist-info/" not in name}
    want = expected()
    for name in sorted(want - held):
        print(f"missing from the wheel: {name}")
    for name in sorted(held - want):
        print(f"in the wheel but not in the checkout: {name}")
    print(f"{Path(wheel).name}: {len(held)} files, {len(want)} expected")
    return 0 if held == want else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
