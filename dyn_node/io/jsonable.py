"""JSON's plain types for NumPy and Python scalars: one rule for the check's records and the
evidence (NaN → null, ±inf → "inf"/"-inf", NumPy bools and numbers → Python's)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np


def json_scalar(v: Any) -> Any:
    """``v`` as a plain JSON scalar when it is a bool or a number; anything else unchanged."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return None
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(v, np.integer):
        return int(v)
    return v
