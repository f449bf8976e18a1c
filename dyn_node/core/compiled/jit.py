"""The compile options and argument types every kernel module of ``compiled`` shares.

Public kernels are compiled for exactly these types when their module is imported (or loaded
from the cache): any layout, read-only or not, one specialisation each, so no call ever stops to
compile. Anything else (float32, integers) is a TypeError, not a silent recompilation.
"""
from __future__ import annotations

from numba import types

# nogil: a check in the node's worker thread does not stall joint_states; cache: compiled once; error_model "numpy": x/0 gives inf or
# NaN as in NumPy (no ZeroDivisionError branch in every loop)
_JIT = dict(cache=True, nogil=True, error_model="numpy")

_f8 = types.float64
_i8 = types.int64
_V = types.Array(_f8, 1, "A", readonly=True)
_M = types.Array(_f8, 2, "A", readonly=True)
_B = types.Array(types.boolean, 1, "A", readonly=True)
_I = types.Array(_i8, 1, "A", readonly=True)
_pair = types.UniTuple(_f8, 2)
