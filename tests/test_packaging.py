"""The wheel's package list (setup.py) names every folder of modules under
pipeline/rotcal/ as a subpackage of rotcal: a folder left out (or one without its
__init__.py) installs a rotcal that fails on import (issue 12). `.ci/run`
builds the wheel itself and checks its file list with .ci/check_wheel.py."""

import runpy

import setuptools

from testdata import REPO


def test_every_folder_of_modules_under_pipeline_is_a_package(monkeypatch):
    captured = {}
    monkeypatch.setattr(setuptools, "setup", lambda **options: captured.update(options))
    runpy.run_path(str(REPO / "setup.py"))
    pipeline = REPO / "pipeline" / "rotcal"
    folders = {path.parent.relative_to(pipeline) for path in pipeline.rglob("*.py")}
    expected = {".".join(("rotcal", *folder.parts)) for folder in folders}
    assert expected <= set(captured["packages"])
    assert all((pipeline / folder / "__init__.py").is_file() for folder in folders)
