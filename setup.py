"""Packages found, not listed: every package under pipeline/ (rotcal and its
stages), plus the two resource packages schemas/ and configs/."""

from setuptools import find_packages, setup

setup(packages=[*find_packages("pipeline"), "rotcal_schemas", "rotcal_configs"])
