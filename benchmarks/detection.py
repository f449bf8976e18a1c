"""Issue 19's detection latency, a sub-result of the "live" section: from the first sample of a
push in the simulated stack to dyn_node's first ``contact`` status, over many pushes
(benchmarks/contact_bench.py measures; this module summarises it beside the observer's time
constant 1/K and its 95 % rise 3/K).
"""
from __future__ import annotations

import math
import statistics
import traceback
from pathlib import Path
from typing import Any

from .common import NotAvailable, percentile

#: pushes a full run needs for the median and p95 to mean something (issue 19)
MIN_PUSHES = 20


def summarise(res: dict[str, Any]) -> dict[str, Any]:
    """Median and p95 of ``latencies_ms``, 1/K and 3/K (ms) from ``observer_gain`` (1/s)."""
    lat = [float(x) for x in res.get("latencies_ms", [])]
    if not lat:
        return dict(status="not available: contact_bench measured no latency", raw=res)
    k = res.get("observer_gain", math.nan)
    k = float(k[0] if isinstance(k, (list, tuple)) else k)   # one value applies to every joint
    return dict(status="ok", pushes=int(res.get("pushes", len(lat))), detected=len(lat),
                missed=int(res.get("missed", 0)), median_ms=statistics.median(lat),
                p95_ms=percentile(lat, 95), max_ms=max(lat), observer_gain=k,
                one_over_k_ms=1e3 / k, three_over_k_ms=3e3 / k,
                force_n=res.get("force_n"), what=res.get("what", ""),
                min_duration_ms=res.get("contact_min_duration_ms"),
                enough=len(lat) >= MIN_PUSHES, latencies_ms=lat, press=res.get("press"))


def run(quick: bool = False, smoke: bool = False) -> dict[str, Any]:
    """contact_bench's measurement summarised, or why it is not available (never raises)."""
    if not (Path(__file__).parent / "contact_bench.py").exists():
        return dict(status="not available: benchmarks/contact_bench.py does not exist yet")
    try:
        from . import contact_bench
    except ImportError as exc:
        return dict(status=f"not available: benchmarks.contact_bench: {exc}")
    fn = getattr(contact_bench, "run", None)
    if fn is None:
        return dict(status="not available: benchmarks.contact_bench has no run()")
    try:
        return summarise(fn(quick=quick, smoke=smoke))
    except NotAvailable as exc:
        return dict(status=f"not available: {exc}")
    except Exception as exc:  # H5's stack failing must not hide the live rows
        traceback.print_exc()
        return dict(status=f"failed: {type(exc).__name__}: {exc}")
