"""dyn-audit's stages one at a time: read (the bag and its configurations), replay (the inputs
through the node's core, without the re-check), re-check (recorded outputs against recomputed
ones), evidence and verdict (on a hand-made replay result). test_audit runs them chained."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_audit import MS, PARAMS, T0, make_bag, trajectory_msg  # noqa: E402

from dyn_node.audit.bag_audit import (ROLE_GRAVITY, ROLE_ID, Audit, AuditError, AuditOptions,  # noqa: E402
                            Rechecker, Replay, Roles, add_verdict, build_evidence, open_bag, stream)
from dyn_node.errors import CONTROL_ERROR, EVALUATION_ERROR, STATE_ERROR  # noqa: E402
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_VIOLATIONS  # noqa: E402


def _source(bag: Path, tmp_path: Path):
    return Audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False,
                              progress=False)).read()


def test_read_gives_the_bags_configurations(tmp_path):
    later = {"parameters": PARAMS + "    payload:\n      mass: 1.5\n",
             "effective_log_time_ns": str(T0 + 700 * MS)}
    source = _source(make_bag(tmp_path / "bag", n=50, later_metadata=later), tmp_path)
    assert source.model_source == "bag:parameters"  # robot_model: panda, as recorded
    assert source.overrides == {}
    assert [c.since_ns for c in source.configurations] == [None, T0 + 700 * MS]
    assert source.first.model.name == "panda"
    assert source.configurations[1].model.payload.mass == 1.5
    assert source.first.model.payload.mass == 0.0


def test_read_refuses_a_file_that_is_not_mcap(tmp_path):
    f = tmp_path / "x.mcap"
    f.write_bytes(b"not an mcap file at all")
    with pytest.raises(AuditError) as e:
        open_bag(str(f))
    assert e.value.code == "bag_unreadable"


def test_replay_alone_counts_inputs_gaps_invalid_and_trajectories(tmp_path):
    """1000 messages at 1 kHz, 300 dropped (one gap of 301 ms, shorter than stale_timeout
    0.5 s), two invalid, one trajectory: the replay's counts, with no re-check attached."""
    bag = make_bag(tmp_path / "bag", n=1000, drop=range(400, 700),
                   invalid={100: "nan", 101: "missing"},
                   trajectories=[(200, trajectory_msg(T0 + 200 * MS))])
    source = _source(bag, tmp_path)
    replay = Replay(source.configurations, gap_threshold_s=0.05)
    assert replay.sink is None
    n = stream(source.reader, Roles(), replay, None)
    r = replay.finish()
    assert n == 700 + 1  # joint_states kept + the trajectory
    assert (r.counts.received, r.counts.accepted) == (700, 698)
    assert r.invalid.total == 2 and sum(r.invalid_by_reason.values()) == 2
    assert [e["t_ns"] for e in r.invalid.items] == [T0 + 100 * MS, T0 + 101 * MS]
    assert r.gaps.total == 1
    assert r.gaps.items == [{"start_ns": T0 + 399 * MS, "end_ns": T0 + 700 * MS}]
    assert r.stale.total == 0
    assert r.js_topics == {"/joint_states"}
    assert r.last_log_ns == T0 + 999 * MS
    assert r.trajectories.total == 1
    assert r.trajectories.items[0]["request"] == "execute"
    assert r.trajectories.items[0]["t_ns"] == T0 + 200 * MS + 500
    assert r.live.series is not None and r.live.peak_util.shape == (7,)


def test_replay_gives_the_same_result_with_and_without_the_recheck(tmp_path):
    bag = make_bag(tmp_path / "bag", n=600, outputs=True, drop=range(300, 350))
    results = []
    for with_recheck in (False, True):
        source = _source(bag, tmp_path)
        recheck = Rechecker(source.reader.known_topics()) if with_recheck else None
        replay = Replay(source.configurations, sink=recheck)
        stream(source.reader, Roles(), replay, recheck)
        r = replay.finish()
        results.append((r.counts.accepted, r.gaps.items, r.live.peak_util.tolist(),
                        r.live.peak_t.tolist()))
    assert results[0] == results[1]
    assert results[0][0] == 550


def test_recheck_finds_the_one_perturbed_output(tmp_path):
    """The bag's inverse_dynamics output at input 400 has 1e-9 N·m added to joint 3: the
    re-check matches every output, finds gravity identical and that one difference."""
    bag = make_bag(tmp_path / "bag", n=600, outputs=True, perturb=400)
    source = _source(bag, tmp_path)
    recheck = Rechecker(source.reader.known_topics())
    replay = Replay(source.configurations, sink=recheck)
    stream(source.reader, Roles(), replay, recheck)
    replay.finish()
    res = recheck.result()
    g, tau = res.checks[ROLE_GRAVITY], res.checks[ROLE_ID]
    assert (g.matched, g.unmatched, g.max_diff) == (600, 0, 0.0)
    assert (tau.matched, tau.unmatched) == (600, 0)
    assert tau.max_diff == pytest.approx(1e-9, abs=1e-13)
    assert tau.worst["stamp_ns"] == T0 + 400 * MS
    assert res.unanswered[ROLE_GRAVITY] == 0 and res.unanswered[ROLE_ID] == 0
    assert res.topics == {ROLE_GRAVITY: "/dyn_node/gravity_torque",
                          ROLE_ID: "/dyn_node/inverse_dynamics"}
    assert res.latency_stamp.n == 600  # every gravity output, 200 µs after its input
    assert res.latency_stamp.min == pytest.approx(200e-6, abs=1e-12)


def _hand_made(tmp_path):
    """A real (short) bag's source, and a replay result edited by hand: one effort episode on
    joint 2 from 10 to 20 ms peaking at 90 N·m (limit 87) at 15 ms, one invalid message, one gap."""
    source = _source(make_bag(tmp_path / "bag", n=50), tmp_path)
    replay = Replay(source.configurations)
    stream(source.reader, Roles(), replay, None)  # the reader's statistics: times from T0
    r = replay.finish()
    assert r.live.episodes.total == 0 and r.invalid.total == 0 and r.gaps.total == 0
    r.live.episodes.closed.append({"j": 1, "kind": "effort", "start": T0 + 10 * MS,
                                   "end": T0 + 20 * MS, "peak_t": T0 + 15 * MS, "peak": 90.0,
                                   "limit": 87.0, "n": 11, "sev": 90.0 / 87.0})
    r.live.episodes.total = 1
    r.invalid.add({"t_ns": T0 + 5 * MS, "reason": "position[3] is NaN", "code": "nan", "topic": "/js"})
    r.invalid_by_reason["nan"] = 1
    r.gaps.add({"start_ns": T0 + 30 * MS, "end_ns": T0 + 40 * MS})
    return source, r


def test_evidence_from_a_hand_made_replay_result(tmp_path):
    source, r = _hand_made(tmp_path)
    opts = AuditOptions(bag=str(tmp_path / "bag"))
    recheck = Rechecker([]).result()
    rec = build_evidence(opts, source, Roles(), r, recheck)
    (v,) = rec.outputs["violations"]
    assert (v["joint"], v["kind"], v["unit"], v["messages"]) == ("panda_joint2", "effort", "N·m", 11)
    assert v["start_s"] == pytest.approx(0.010, abs=1e-12)
    assert v["end_s"] == pytest.approx(0.020, abs=1e-12)
    assert v["peak_time_s"] == pytest.approx(0.015, abs=1e-12)
    assert v["peak_ratio"] == 90.0 / 87.0
    assert rec.outputs["violation_episodes_total"] == 1
    assert rec.outputs["recheck"] == {}  # no outputs compared: no section per topic
    q = rec.input_quality
    assert q["invalid_messages"]["count"] == 1
    assert q["invalid_messages"]["examples"][0]["time_s"] == pytest.approx(0.005, abs=1e-12)
    assert q["gaps_total"] == 1 and q["gaps"][0]["duration_s"] == pytest.approx(0.010, abs=1e-12)
    assert rec.inputs["message_counts"] == {"/joint_states": 50}
    assert rec.configuration["model"]["source"] == "bag:parameters"


def test_verdict_of_a_hand_made_replay_result(tmp_path):
    source, r = _hand_made(tmp_path)
    rec = build_evidence(AuditOptions(bag=str(tmp_path / "bag")), source, Roles(), r,
                         Rechecker([]).result())
    code = add_verdict(rec, source, r, gap_threshold_s=0.05)
    assert code == EXIT_VIOLATIONS
    assert rec.verdict["result"] == "violations" and rec.verdict["exit_code"] == code
    assert rec.verdict["summary"] == ("1 live limit violation episode(s), worst panda_joint2 "
                                      "effort at t = 0.015 s")
    assert set(rec.failure_labels) == {CONTROL_ERROR, STATE_ERROR}
    assert "1 invalid joint_states (nan: 1)" in rec.verdict["findings"]
    assert "1 gap(s) in joint_states longer than 0.05 s" in rec.verdict["findings"]
    rec.to_dict()  # the edited record still validates against the schema


def test_verdict_of_a_clean_replay_and_a_differing_recheck(tmp_path):
    bag = make_bag(tmp_path / "bag", n=300, outputs=True, perturb=100)
    source = _source(bag, tmp_path)
    recheck = Rechecker(source.reader.known_topics())
    replay = Replay(source.configurations, sink=recheck)
    stream(source.reader, Roles(), replay, recheck)
    r = replay.finish()
    rec = build_evidence(AuditOptions(bag=str(bag)), source, Roles(), r, recheck.result())
    assert add_verdict(rec, source, r, gap_threshold_s=0.05) == EXIT_OK
    assert rec.verdict["summary"].startswith("all feasible: 300 joint states, 0 executed trajectories; ")
    assert rec.failure_labels == [EVALUATION_ERROR]
    assert rec.verdict["findings"] == [
        "re-check differs from the recorded outputs on /dyn_node/inverse_dynamics"]
