"""dyn_node.io.jsonable: the one rule for JSON scalars, checked against json.dumps round trips."""
import json
import math

import numpy as np
import pytest

from dyn_node.io.jsonable import json_scalar


@pytest.mark.parametrize("value, expected, kind", [
    (np.float64("nan"), None, type(None)), (float("nan"), None, type(None)),
    (np.float32("inf"), "inf", str), (-math.inf, "-inf", str),
    (np.bool_(True), True, bool), (np.bool_(False), False, bool),
    (np.int64(-3), -3, int), (np.uint8(200), 200, int), (np.float32(0.5), 0.5, float),
    (True, True, bool), (7, 7, int), (1.25, 1.25, float)])
def test_scalars_become_plain_json(value, expected, kind):
    out = json_scalar(value)
    assert type(out) is kind
    assert out == expected
    assert json.loads(json.dumps(out, allow_nan=False)) == expected  # strict JSON: no NaN/Infinity


def test_anything_else_is_returned_as_it_came():
    for v in ("x", None, [1.0, float("nan")], {"a": np.float64(1.0)}):
        assert json_scalar(v) is v
