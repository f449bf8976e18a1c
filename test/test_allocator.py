"""dyn_node.core.live.allocator: freed sample arrays stay mapped, so a repeated check takes no fresh pages.

Each case runs in a child interpreter: the setting is process-wide and the page-fault counts
must start from glibc's defaults.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from dyn_node.core.live.allocator import retain_freed_memory

# What a check does to the heap: many MiB-sized arrays alive at once, then all freed. Minor
# faults are counted over the rounds after the first (which maps the pages in any case).
_CHILD = textwrap.dedent("""
    import json, resource, sys
    import numpy as np
    from dyn_node.core.live.allocator import retain_freed_memory
    calls = {"default": 0, "retain": 1, "retain_twice": 2}[sys.argv[1]]
    applied = [retain_freed_memory() for _ in range(calls)]
    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    def round_():
        arrays = [np.ones(131072) for _ in range(24)]     # 24 x 1 MiB
        return sum(float(a[0]) for a in arrays)
    round_()
    before = faults()
    for _ in range(5):
        round_()
    print(json.dumps({"applied": applied, "faults": faults() - before}))
""")

_PAGES_PER_ROUND = 24 * (1 << 20) // 4096


def _run(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def glibc() -> None:
    if _run("retain")["applied"] != [True]:
        pytest.skip("the C library is not glibc (no mallopt): the setting does not apply")


def test_freed_arrays_stay_mapped_across_rounds(glibc):
    default, kept = _run("default"), _run("retain")
    # glibc's defaults give the 24 MiB back after each round, so every round faults it in again:
    # the premise that makes the setting worth having on this machine
    assert default["faults"] > 5 * _PAGES_PER_ROUND // 2
    assert default["applied"] == [] and kept["applied"] == [True]
    assert kept["faults"] < _PAGES_PER_ROUND // 10


def test_repeated_call_applies_again_and_keeps_the_setting(glibc):
    # two entry points in one process: the second call must neither fail nor undo the first
    twice = _run("retain_twice")
    assert twice["applied"] == [True, True]
    assert twice["faults"] < _PAGES_PER_ROUND // 10


def test_rejects_negative_sizes():
    with pytest.raises(ValueError):
        retain_freed_memory(keep_bytes=-1)
    with pytest.raises(ValueError):
        retain_freed_memory(heap_block_bytes=-1)
