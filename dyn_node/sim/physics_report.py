"""EvidenceRecords and plots of ``dyn_sim --check-physics`` (see :mod:`dyn_node.sim.physics_check`).

Each check writes ``DIR/<check>/evidence.json`` (kind ``check``, the nominal run's headline
numbers in the top-level ``figures``, every run under ``outputs.physics``) and a PNG plot.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dyn_node.audit.evidence import EvidenceRecord, metric_definitions, utc_now
from dyn_node.core.robot.model import RobotModel
from dyn_node.errors import EVALUATION_ERROR


def _record(model: RobotModel, *, source: str = "robot_model", check: str, started: str, seconds: float, passed: bool,
            summary: str, findings: list[str]) -> EvidenceRecord:
    rec = EvidenceRecord(kind="check", tool="dyn_sim --check-physics")
    rec.started_utc = started
    rec.inputs = {"bag": "", "files": [], "topics": [], "message_counts": {},
                  "time_span": {"start_ns": None, "end_ns": None, "duration_s": 0.0}}
    rec.configuration = {
        "model": {"name": model.name, "source": source, "urdf_sha256": model.urdf_hash,
                  "joint_names": list(model.joint_names), "dof": model.nv,
                  "gravity_m_s2": list(model.gravity)},
        "limits": model.limits.to_dict(), "parameters": {"check": check}, "overrides": {}}
    rec.input_quality = {"gaps": [], "stale_periods": [], "out_of_order": {"count": 0, "examples": []},
                         "invalid_messages": {"count": 0, "by_reason": {}, "examples": []},
                         "unreadable_ranges": []}
    rec.metric_definitions = metric_definitions("physics")
    rec.seed = {"used": False, "value": None, "note": "deterministic: MuJoCo from a fixed initial "
                "state, no noise; the same version gives identical numbers"}
    if not passed:
        rec.add_label(EVALUATION_ERROR)
    rec.verdict = {"result": "feasible" if passed else "violations", "exit_code": 0 if passed else 1,
                   "summary": summary, "partial": False, "findings": findings}
    rec.duration_s = seconds
    rec.finished_utc = utc_now()
    return rec


def _outputs(physics: dict[str, Any]) -> dict[str, Any]:
    return {"trajectories": [], "effort": {"per_joint": []}, "violations": [], "controller_states": {},
            "recheck": {}, "latency": {}, "physics": physics}


def _run_summary(run: dict[str, Any], drop: tuple[str, ...]) -> dict[str, Any]:
    return {k: v for k, v in run.items() if k not in drop}


def write_free_motion(out: Path, model: RobotModel, result: dict[str, Any], *, q0: np.ndarray,
                      started: str, seconds: float) -> dict[str, Any]:
    """``out/free_motion/evidence.json`` and ``energy.png``; returns the record."""
    out.mkdir(parents=True, exist_ok=True)
    nom = result["nominal"]
    drop = ("t", "q", "v", "potential", "kinetic")
    every = max(1, len(nom["t"]) // 300)  # the nominal trajectory, decimated for the record
    physics = {
        "initial_state": {"q": q0, "v": np.zeros_like(q0)},
        "settings": {"controller": "off", "damping": 0.0, "frictionloss": 0.0, "joint_limits": "off",
                     "contacts": "off", "armature": "URDF/limits armature (in M and in E)",
                     "duration_s": float(nom["t"][-1] + nom["timestep_s"])},
        "nominal": _run_summary(nom, drop), "runs": [_run_summary(r, drop) for r in result["runs"]],
        "halving": result["halving"], "tolerance": result["tolerance"],
        "trajectory": {"t_s": nom["t"][::every], "q": nom["q"][::every],
                       "energy_j": (nom["potential"] + nom["kinetic"])[::every]}}
    passed = result["passed"]
    summary = (f"free motion ({nom['integrator']}, {nom['timestep_s'] * 1e3:g} ms): energy_error_rel "
               f"{nom['energy_error_rel']:.3g} {'<' if passed else '≥'} {result['tolerance']:g}")
    rec = _record(model, check="free_motion", started=started, seconds=seconds, passed=passed,
                  summary=summary, findings=[] if passed else [summary])
    rec.outputs = _outputs(physics)
    rec.figures = {"energy_error_rel": nom["energy_error_rel"]}
    d = rec.write(out / "evidence.json")
    _plot_energy(out / "energy.png", result)
    return d


def write_contact(out: Path, model: RobotModel, result: dict[str, Any], *, started: str,
                  seconds: float) -> dict[str, Any]:
    """``out/contact/evidence.json`` and ``normal_force.png``; returns the record."""
    out.mkdir(parents=True, exist_ok=True)
    nom = result["nominal"]
    drop = ("t_hold", "normal_force", "t_press", "normal_force_press")
    physics = {"initial_state": {"q": np.asarray(result["q0"]), "v": np.zeros(model.nv)},
               "scene": result["scene"], "nominal": _run_summary(nom, drop),
               "perturbed": [_run_summary(r, drop) for r in result["perturbed"]],
               "tolerances": result["tolerances"],
               "trajectory": {"t_s": nom["t_hold"][::10], "normal_force_n": nom["normal_force"][::10]}}
    passed = result["passed"]
    summary = (f"contact (press on the table): max_penetration_m {nom['max_penetration_m']:.3g}, "
               f"normal_force_n {nom['normal_force_n']:.4g}, variation {nom['normal_force_variation_rel']:.2g}, "
               f"balance residual {nom['balance_residual_rel']:.2g}: {'holds' if passed else 'fails'}")
    rec = _record(model, check="contact", started=started, seconds=seconds, passed=passed,
                  summary=summary, findings=list(result["failures"]))
    rec.outputs = _outputs(physics)
    rec.figures = {"max_penetration_m": nom["max_penetration_m"], "normal_force_n": nom["normal_force_n"]}
    d = rec.write(out / "evidence.json")
    _plot_force(out / "normal_force.png", result)
    return d


def _plot_energy(path: Path, result: dict[str, Any]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in result["runs"]:
        E = r["potential"] + r["kinetic"]
        ax.plot(r["t"], np.abs(E - E[0]) / r["peak_kinetic_j"],
                label=f"{r['integrator']} {r['timestep_s'] * 1e3:g} ms: {r['energy_error_rel']:.2g}")
    ax.axhline(result["tolerance"], color="k", ls="--", lw=0.8, label="tolerance")
    ax.set(yscale="log", xlabel="t (s)", ylabel="|E(t) − E(0)| / peak KE",
           title="free motion: energy error by integrator and timestep")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_force(path: Path, result: dict[str, Any]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, hold) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [3, 2]})
    for r in [result["nominal"], *result["perturbed"]]:
        label = f"{r['label']}: pen. {r['max_penetration_m'] * 1e3:.2f} mm"
        ax.plot(np.concatenate([r["t_press"], r["t_hold"]]),
                np.concatenate([r["normal_force_press"], r["normal_force"]]), label=label, lw=0.8)
        hold.plot(r["t_hold"], r["normal_force"], label=label)
    ax.axvspan(result["nominal"]["t_hold"][0], result["nominal"]["t_hold"][-1], color="0.9")
    ax.set(xlabel="t (s)", ylabel="normal force (N)", title="contact: the press (shaded: the held second)")
    hold.set(xlabel="t (s)", title="the held second")
    hold.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
