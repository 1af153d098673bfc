"""Packages found, not listed: `rotcal` and every package under pipeline/
(the import name differs from the folder, which setuptools' automatic
discovery cannot map), plus the two resource packages."""

from setuptools import find_packages, setup

setup(packages=["rotcal", *(f"rotcal.{name}" for name in find_packages("pipeline")), "rotcal_schemas", "rotcal_configs"])
