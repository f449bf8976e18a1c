"""The benchmark baselines compute the right thing, and the bench harness runs end to end.

Speed is never asserted here: the benchmarks measure it. What is asserted is that each peer the
benchmarks time computes the same torque as Pinocchio (an implementation we did not write) and
the closed-form 2-link arm, so a timing row can never compare against a wrong answer.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from benchmarks import report
from benchmarks.common import SYSTEM_PYTHON, read_proc_cpu, read_vm, system_pykdl
from benchmarks.dynamics_bench import random_states
from benchmarks.mujoco_ref import MujocoInverse
from benchmarks.numpy_rnea import NumpyRNEA
from benchmarks.task_feasibility import TASK_KINDS
from dyn_node.core.robot.model import load_model
from robots import BRANCHED_URDF

REPO = Path(__file__).resolve().parents[1]
ROBOTS = ("panda", "ur5", "planar_2link")



def _pin_loop(pm, Q, V, A) -> np.ndarray:
    data = pm.createData()
    return np.array([pin.rnea(pm, data, Q[i], V[i], A[i]) for i in range(len(Q))])


@pytest.mark.parametrize("robot", ROBOTS)
def test_numpy_rnea_matches_pinocchio(robot: str) -> None:
    model = load_model(builtin=robot)
    Q, V, A = random_states(model, 300, seed=11)
    ref = _pin_loop(model.pin_model, Q, V, A)
    r = NumpyRNEA(model.pin_model)
    np.testing.assert_allclose(r.rnea_batch(Q, V, A), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(r.rnea(Q[7], V[7], A[7]), ref[7], rtol=0, atol=1e-9)
    assert np.max(np.abs(ref)) > 1.0  # the states exercise real torques, not near-zero ones


def test_numpy_rnea_branched_tree_prismatic_unaligned_armature() -> None:
    pm = load_model(urdf=BRANCHED_URDF).pin_model.copy()
    kinds = {pm.joints[i].shortname() for i in range(1, pm.njoints)}
    assert {"JointModelPrismaticUnaligned", "JointModelRevoluteUnaligned", "JointModelPX"} <= kinds
    pm.armature = np.array([0.1, 0.2, 0.05, 0.3, 0.02, 0.01])
    pm.gravity.linear = np.array([1.0, -2.0, -9.0])
    rng = np.random.default_rng(3)
    Q, V, A = (rng.uniform(-1, 1, (200, pm.nv)) for _ in range(3))
    np.testing.assert_allclose(NumpyRNEA(pm).rnea_batch(Q, V, A), _pin_loop(pm, Q, V, A),
                               rtol=0, atol=1e-9)


def test_numpy_rnea_two_link_closed_form() -> None:
    """The textbook manipulator equation of the 2-link arm (issue 2), independent of Pinocchio."""
    m1, m2, l1, l2, g = 1.5, 1.0, 0.5, 0.4, 9.81
    model = load_model(builtin="planar_2link")
    Q, V, A = random_states(model, 100, seed=5)
    tau = NumpyRNEA(model.pin_model).rnea_batch(Q, V, A)
    for (q1, q2), (v1, v2), acc, t in zip(Q, V, A, tau):
        c1, c2, c12, s2 = np.cos(q1), np.cos(q2), np.cos(q1 + q2), np.sin(q2)
        M = np.array([[m1 * l1**2 + m2 * (l1**2 + l2**2 + 2 * l1 * l2 * c2), m2 * (l2**2 + l1 * l2 * c2)],
                      [m2 * (l2**2 + l1 * l2 * c2), m2 * l2**2]])
        h = -m2 * l1 * l2 * s2
        C = np.array([[h * v2, h * (v1 + v2)], [-h * v1, 0.0]])
        grav = np.array([(m1 + m2) * g * l1 * c1 + m2 * g * l2 * c12, m2 * g * l2 * c12])
        np.testing.assert_allclose(t, M @ acc + C @ np.array([v1, v2]) + grav, rtol=0, atol=1e-9)


@pytest.mark.parametrize("robot", ROBOTS)
def test_mujoco_reference_matches_pinocchio(robot: str) -> None:
    model = load_model(builtin=robot)
    Q, V, A = random_states(model, 100, seed=2)
    mj = MujocoInverse(model)
    out = np.array([mj.rnea(Q[i], V[i], A[i]) for i in range(len(Q))])
    np.testing.assert_allclose(out, _pin_loop(model.pin_model, Q, V, A), rtol=0, atol=1e-9)


@pytest.mark.timeout(60)
def test_kdl_worker_matches_pinocchio_or_reports_why() -> None:
    ok, why = system_pykdl()
    if not ok:
        # the bench row then says why (test_bench_harness_smoke checks the row carries the reason)
        pytest.skip(f"PyKDL unavailable: {why}")
    for robot in ("panda", "ur5"):
        model = load_model(builtin=robot)
        Q, V, A = random_states(model, 40, seed=9)
        job = dict(urdf=model.urdf, joint_names=list(model.joint_names),
                   locked=dict(model.locked_joints),
                   gravity=[float(g) for g in model.pin_model.gravity.linear],
                   Q=Q.tolist(), V=V.tolist(), A=A.tolist(), repeats=1)
        p = subprocess.run([SYSTEM_PYTHON, str(REPO / "benchmarks" / "kdl_worker.py")],
                           input=json.dumps(job), capture_output=True, text=True,
                           env={"PATH": "/usr/bin:/bin"}, timeout=60)
        assert p.returncode == 0, p.stderr
        tau = np.array(json.loads(p.stdout)["tau"])
        np.testing.assert_allclose(tau, _pin_loop(model.pin_model, Q, V, A), rtol=0, atol=1e-9)


@pytest.mark.timeout(60)
def test_proc_readers_see_this_process() -> None:
    t0 = read_proc_cpu(os.getpid())
    x = 0.0
    # burn CPU until our own CPU time moves (the kernel counts in clock ticks); a reader that never
    # sees it move fails by the timeout
    while read_proc_cpu(os.getpid()) == t0:
        for i in range(100_000):
            x += i * 0.5
    assert read_proc_cpu(os.getpid()) > t0
    assert read_vm(os.getpid(), "VmHWM") >= read_vm(os.getpid(), "VmRSS") > 1.0


def test_summary_markers_replaced_only_between_them(tmp_path) -> None:
    summary = tmp_path / "performance.md"
    assert not report.replace_between_markers(summary, "x")
    summary.write_text("intro\n")
    assert not report.replace_between_markers(summary, "x")
    assert summary.read_text() == "intro\n"
    summary.write_text(f"intro\n{report.BEGIN}\nold\n{report.END}\noutro\n")
    assert report.replace_between_markers(summary, "new table")
    assert summary.read_text() == f"intro\n{report.BEGIN}\nnew table\n{report.END}\noutro\n"


@pytest.mark.timeout(120)
def test_bench_harness_smoke(tmp_path, ros_domain: int) -> None:
    """`python -m benchmarks.run --smoke` over dynamics, live (bare republisher only) and
    feasibility (one measuring process each way) writes bench.json, the docs page and the summary
    section, whose link to the docs page resolves from where it lives; every dynamics peer agreed
    with dyn_node."""
    summary = tmp_path / "summary" / "performance.md"
    summary.parent.mkdir()
    summary.write_text(f"# x\n{report.BEGIN}\n{report.END}\n")
    env = dict(os.environ, DYN_BENCH_DOMAIN=str(ros_domain))
    p = subprocess.run([sys.executable, "-m", "benchmarks.run", "--smoke", "--only", "dynamics,live,feasibility",
                        "--out", str(tmp_path / "out"), "--docs", str(tmp_path / "BENCH.md"),
                        "--summary", str(summary)], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=170)
    assert p.returncode == 0, p.stderr[-2000:]
    doc = json.loads((tmp_path / "out" / "bench.json").read_text())
    # the versions the figures were taken with are the ones installed (the modules' own attributes)
    import mujoco

    versions = doc["machine"]["versions"]
    assert {k: versions[k] for k in ("python", "numpy", "pinocchio", "mujoco")} == {
        "python": platform.python_version(), "numpy": np.__version__,
        "pinocchio": pin.__version__, "mujoco": mujoco.__version__}, versions
    assert versions["rclpy"][:1].isdigit(), versions   # a version, not "not installed"
    dyn = doc["sections"]["dynamics"]
    assert dyn["status"] == "ok", dyn
    rows = dyn["result"]["rows"]
    assert {r["robot"] for r in rows} == set(ROBOTS)
    for r in rows:
        if r["status"] == "ok":
            assert r["max_abs_diff_Nm"] <= 1e-9 and r["batch_s"] > 0
        else:  # only an optional peer may be missing, and it must say why
            assert r["impl"] == "PyKDL ChainIdSolver_RNE" and "not installed" in r["status"], r
    live = doc["sections"]["live"]
    assert live["status"] == "ok", live
    bare = live["result"]["rows"][0]
    assert bare["status"] == "ok", bare
    w = bare["windows"][0]
    assert w["sent"] > 0 and 0 <= w["received"] <= w["sent"] and w["p50_us"] > 0
    feas = doc["sections"]["feasibility"]
    assert feas["status"] == "ok", feas
    f = feas["result"]
    assert f["processes"] == 1 and f["check_no_margin_s"] > 0 and f["rnea_loop_s"] > 0
    assert f["heap_retained"] == (platform.libc_ver()[0] == "glibc")   # mallopt is glibc's
    # the figure is the retained-heap process's, and the setting it reports does what it claims:
    # under glibc's defaults each repeated check faults its sample arrays in again (thousands)
    assert f["page_faults_per_check"] == f["heap"]["retain"]["faults"]
    if f["heap_retained"]:
        assert f["heap"]["retain"]["faults"] < f["heap"]["default"]["faults"] // 10, f["heap"]
    assert set(f["heap"]) == {"default", "retain"} and f["heap"]["default"]["check_s"] > 0
    task = f["task"]     # issue 18's row: measured, or saying why not
    assert task["status"] == "ok", task
    assert task["check_no_margin_s"] > 0 and task["ratio_no_margin"] > 0
    assert task["worst_task"]["kind"] in TASK_KINDS
    assert "detection" not in live["result"]   # the pushes are not part of the smoke run
    text = (tmp_path / "BENCH.md").read_text()
    assert "## Dynamics" in text and "pinocchio.rnea Python loop" in text and "SMOKE" in text
    summary_text = summary.read_text()
    assert summary_text.startswith("# x\n" + report.BEGIN)
    assert "[../BENCH.md](../BENCH.md)" in summary_text and (summary.parent / "../BENCH.md").is_file()


def test_publisher_efforts_are_the_free_motion_torque() -> None:
    """`ros_publisher --effort` sends τ = RNEA(q, q̇, q̈) of the sample it sends (checked against
    MuJoCo), so the live bench's observer row runs on a robot in free motion."""
    from benchmarks.ros_publisher import HOME, NAMES, model_effort

    model = load_model(builtin="panda")
    assert list(model.joint_names) == NAMES
    effort, mj = model_effort(), MujocoInverse(model)
    for t in (0.0, 0.37, 2.5):
        q = [h + 0.3 * np.sin(t + i) for i, h in enumerate(HOME)]
        v = [0.3 * np.cos(t + i) for i in range(7)]
        a = [-0.3 * np.sin(t + i) for i in range(7)]
        np.testing.assert_allclose(effort(q, v, a), mj.rnea(np.array(q), np.array(v), np.array(a)),
                                   rtol=0, atol=1e-9)


def test_detection_summary_median_p95_and_time_constant() -> None:
    from benchmarks import detection

    lat = [float(x) for x in np.random.default_rng(4).permutation(np.arange(1.0, 26.0))]
    s = detection.summarise(dict(latencies_ms=lat, pushes=26, missed=1, observer_gain=[50.0],
                                 contact_min_duration_ms=20.0))
    assert s["status"] == "ok" and s["detected"] == 25 and s["pushes"] == 26 and s["enough"]
    assert s["median_ms"] == 13.0 and s["p95_ms"] == 24.0 and s["max_ms"] == 25.0
    assert (s["one_over_k_ms"], s["three_over_k_ms"]) == (20.0, 60.0)
    assert detection.summarise(dict(latencies_ms=[]))["status"].startswith("not available")
    assert not detection.summarise(dict(latencies_ms=[5.0], observer_gain=10.0))["enough"]
    text = report._detection_md(s)
    assert "| 25 / 26 | — | 13 | 24 | 25 | 20 | 60 | 20 |" in text, text


def test_task_row_covers_every_issue18_kind() -> None:
    """The #18 row's configuration names every kind issue 18 settles, and a result missing a
    place or kind is reported as not covering it (so the row never times a partial check)."""
    from types import SimpleNamespace

    from benchmarks import task_feasibility as T

    places = T.expected_places()
    assert set().union(*places.values()) == set(T.TASK_KINDS)
    sections = T.task_sections()
    assert set(sections["frame_limits"]) | {"robot_limits", "base_limits", "grasp"} == set(places)
    full = {p: {k: {} for k in kinds} for p, kinds in places.items()}
    assert T.coverage_gap(SimpleNamespace(per_frame=full)) is None
    del full["base_limits"]["tipping"]
    assert T.coverage_gap(SimpleNamespace(per_frame=full)) == \
        "the check did not report base_limits: tipping"
    row = T.row([], None, "why")
    assert row["status"] == "not available: why"
    assert report._task_rows(row, None, 0.01) == [[T.WHAT, "not available: why", "10", "—",
                                                   "≤ 2.0× (issue 18)"]]


def test_live_pairs_and_contact_comparisons(monkeypatch) -> None:
    """The live section's ratios from fake subject rows: the contact row's p99 ratio is the
    median over pairs of (b) fed efforts and (e) run apart from the rows, its loss the worst
    run's (the row's included), the recording overhead over (c)/(d)."""
    from benchmarks import detection, live_bench

    p99 = {"bare": [100.0], "minimal": [200.0], "minimal_effort": [200.0, 400.0, 100.0, 100.0, 100.0],
           "dyn_node": [100.0, 100.0, 100.0], "dyn_node_record": [100.0] * 3,
           "dyn_node_contact": [100.0, 100.0, 800.0, 90.0, 300.0, 50.0]}
    loss = {"dyn_node_contact": [0.03, 0.0, 0.02, 0.0, 0.0, 0.0]}
    calls: list[str] = []
    probe_args: dict[str, list[str]] = {}

    def fake(s, rates, window, ready_timeout, repeat_first, settle_s=live_bench.SETTLE_S):
        assert settle_s == live_bench.SETTLE_S > 0  # no window holds a subject's start-up
        k = s["key"]
        n = calls.count(k)
        calls.append(k)
        probe_args[k] = s.get("probe_args", [])
        return dict(key=k, subject=s["name"], what="", status="ok", p99_us_1k=p99[k][n],
                    p50_us_1k=50.0, cpu_share_1k=0.2 + 0.02 * (k == "dyn_node_record"),
                    cpu_us_per_output_1k=200.0, loss_1k=loss.get(k, [0.0] * 6)[n],
                    also_loss_1k=0.0, max_rate_no_loss_hz=1000.0, windows=[])

    monkeypatch.setattr(live_bench, "run_subject", fake)
    monkeypatch.setattr(live_bench, "_contact_reason", lambda: None)
    monkeypatch.setattr(detection, "run", lambda **kw: dict(status="not available: test"))
    out = live_bench.run()
    c = out["comparisons"]
    assert calls.count("minimal") == 1 and calls.count("minimal_effort") == live_bench.CONTACT_PAIRS == 5
    assert calls.count("dyn_node_contact") == 6
    # both ends of a pair get the same joint_states: (b) is fed efforts like (e)
    assert "--effort" in probe_args["minimal_effort"] and "--effort" in probe_args["dyn_node_contact"]
    assert "--effort" not in probe_args["minimal"]
    assert out["p99_contact_over_minimal_1k_by_pair"] == [0.5, 2.0, 0.9, 3.0, 0.5]
    assert c["p99_contact_over_minimal_1k"] == 0.9 and c["loss_contact_1k"] == 0.03
    assert c["p99_contact_over_dyn_node_1k"] == 1.0
    assert out["recording_cpu_overhead_1k_by_pair"] == pytest.approx([0.1] * 3, abs=1e-12)
    assert out["detection"] == {"status": "not available: test"}
