"""The frame kernels (dyn_node.core.check.frames) on the feasibility check's own Panda samples, beside the
Python pinocchio.rnea loop on the same samples.

The subject is what the frame, energy and base constraints of issue 18 need per sample: two
frame points (the flange 0.1 m out, carrying a task wrench, and the hand), M(q) with its
Cholesky factor, g(q), the kinetic energy and effective masses, and the base wrench. Its row
sits in the "feasibility" section (feasibility_bench adds it to its interleaved rounds);
``python -m benchmarks.frames_bench [ROUNDS]`` measures it alone in this process.
"""
from __future__ import annotations

import json
import statistics
import sys
from typing import Callable

import numpy as np

from dyn_node.core.live.allocator import retain_freed_memory
from dyn_node.core.check.frames import FrameKinematics, FramePoint

from .common import median_time

WHAT = ("dyn_node.core.check.frames on the same samples, 1 thread: two frame points (position, velocity, "
        "classical acceleration, angular terms, J_localᵀW), M(q) by CRBA with its Cholesky "
        "factor, g(q), kinetic energy, effective masses, base wrench and centre of mass")


def subjects(model, Q: np.ndarray, V: np.ndarray,
             A: np.ndarray) -> dict[str, Callable[[], object]]:
    """Callables timed beside the loop: everything (``frame_kernels``), and the kinematics of
    the two points alone (``frame_kinematics``)."""
    fk = FrameKinematics(model, [FramePoint("panda_link8", (0.0, 0.0, 0.1),
                                            (0.0, 0.0, 20.0, 0.0, 0.0, 0.0)),
                                 FramePoint("panda_hand")])
    fk.compute(Q[:1], V[:1], A[:1])    # loads the compiled kernel
    return {"frame_kernels": lambda: fk.compute(Q, V, A),
            "frame_kinematics": lambda: fk.compute(Q, V, A, inertia=False, base=False)}


def measure(rounds: int = 15) -> dict:
    """Interleaved rounds of the loop and the subjects on feasibility_bench's samples: median
    time (ms) of each and median per-round ratio to the loop."""
    from .feasibility_subject import setup

    F, dyn, traj, options, loop, (Q, V, A) = setup()
    subj = {"loop": loop, **subjects(dyn.model, Q, V, A)}
    times: dict[str, list[float]] = {k: [] for k in subj}
    for fn in subj.values():
        fn()
    for _ in range(rounds):
        for key, fn in subj.items():
            times[key].append(median_time(fn, 1, warmup=0)[0])
    return dict(n_samples=int(len(Q)), rounds=rounds,
                median_ms={k: 1e3 * statistics.median(v) for k, v in times.items()},
                ratio={k: statistics.median(t / b for t, b in zip(v, times["loop"]))
                       for k, v in times.items() if k != "loop"})


if __name__ == "__main__":
    retain_freed_memory()    # as the node and feasibility_bench's figures run
    print(json.dumps(measure(int(sys.argv[1]) if len(sys.argv) > 1 else 15), indent=1))
