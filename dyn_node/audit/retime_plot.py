"""The retiming plot of dyn-check's ``--out`` report: the input's, the uniform stretch's and the
retimed velocity and torque profiles against their limits (each the largest ratio over the
joints, so one curve per trajectory shows how close to its limits it runs)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dyn_node.core.check.start_segment import stretched
from dyn_node.core.check.trajectory import Trajectory, interpolate


def profile(dynamics: Any, traj: Trajectory, n: int = 1500) -> tuple[np.ndarray, ...]:
    """(t, max_j |q̇_j|/v_j, max_j |τ_j|/τ_j) at n samples of the check's interpolation."""
    lim = dynamics.model.limits
    t = np.linspace(traj.times[0], traj.times[-1], n)
    q, v, a, _ = interpolate(traj, traj.natural_interpolation).evaluate(t)
    tau = dynamics.rnea_batch(q, v, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        vr = np.nan_to_num(np.abs(v) / lim.velocity, posinf=0.0)
        tr = np.nan_to_num(np.abs(tau) / lim.effort, posinf=0.0)
    return t, vr.max(axis=1), tr.max(axis=1)


def write_plot(dynamics: Any, res: Any, dest: Path) -> Path | None:
    """``dest`` (PNG) with the three profiles, or None when there is nothing to draw."""
    if res.input_check is None or res.trajectory is None:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = res.input_check
    curves = []
    source = res.source
    if source is not None:
        curves.append(("input", source))
        k = base.time_scale
        if np.isfinite(k) and k > 0:
            curves.append((f"uniform ×{k * 1.001:.3g}", stretched(source, k * 1.001)))
    curves.append((f"retimed ({res.method})", res.trajectory))
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for label, tr in curves:
        t, vr, tq = profile(dynamics, tr)
        axes[0].plot(t, vr, label=f"{label}: {tr.duration:.3g} s", lw=1)
        axes[1].plot(t, tq, lw=1)
    for ax, what in zip(axes, ("velocity", "torque")):
        ax.axhline(1.0, color="k", ls="--", lw=0.8)
        ax.set_ylabel(f"max |{what}| / limit")
    axes[1].set_xlabel("t (s)")
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"retiming: T* {res.lower_bound:.3g} s, gap {res.gap:.3f}")
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=90)
    plt.close(fig)
    return dest

