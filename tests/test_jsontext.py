"""``json_text``: the layout of the JSON documents rotcal writes for people
(calibration.json, the JSON export, the file listing), checked against
text written out by hand."""

import json
import math

import pytest

from rotcal.jsontext import json_text


def test_matrix_rows_and_objects_one_per_line():
    doc = {"P": [[1.0, 0.5], [-2e-05, 3]], "u": {"value": 1.5, "unit": "m/s^2"}, "names": ["a", "b"],
           "empty": [], "none": {}, "items": [{"k": None}, [True]]}
    assert json_text(doc) == (
        '{\n'
        ' "P": [\n'
        '  [1.0, 0.5],\n'
        '  [-2e-05, 3]\n'
        ' ],\n'
        ' "u": {\n'
        '  "value": 1.5,\n'
        '  "unit": "m/s^2"\n'
        ' },\n'
        ' "names": ["a", "b"],\n'
        ' "empty": [],\n'
        ' "none": {},\n'
        ' "items": [\n'
        '  {\n'
        '   "k": null\n'
        '  },\n'
        '  [true]\n'
        ' ]\n'
        '}\n')
    assert json.loads(json_text(doc)) == doc


def test_numbers_read_back_exactly():
    values = [0.1 + 0.2, 1 / 3, 6.02214076e23, -5e-324, 2.0**-1074, 123456789012345678]
    assert json.loads(json_text({"v": values, "m": [values]})) == {"v": values, "m": [values]}


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_is_refused(bad):
    with pytest.raises(ValueError):
        json_text({"rows": [[1.0, bad]]})
