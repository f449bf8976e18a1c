"""Executed trajectories and questions counted apart: in the evidence record (every entry's
``request``, ``trajectory_counts``), the verdict's summary line dyn-audit prints (and the demo
shows), and the report's trajectories table. Expected numbers come from how the bag was written
(which trajectories were sent to be executed, which asked as check-only questions, which too fast)."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import jsonschema
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet_bags import BagSpec, write_bag  # noqa: E402

from dyn_node.audit.accounting import RequestTally, request_of_role  # noqa: E402
from dyn_node.audit.bag_audit import main as audit_main  # noqa: E402

EXECUTED = (True, False, False, False)        # 1 of 4 too fast
QUESTIONS = (True, False, True, False, False)  # 2 of 5 too fast


@pytest.fixture(scope="module")
def audited(tmp_path_factory):
    root = tmp_path_factory.mktemp("acct")
    bag = write_bag(root, BagSpec("mixed", "panda", 2.0, trajectories=EXECUTED, questions=QUESTIONS))
    out = root / "audit"
    import io
    from contextlib import redirect_stdout

    so = io.StringIO()
    with redirect_stdout(so):
        code = audit_main([str(bag), "--out", str(out)])
    rec = json.loads((out / "evidence.json").read_text())
    schema = json.loads((Path(__file__).resolve().parents[1] / "dyn_node" / "schemas"
                         / "evidence_record.schema.json").read_text())
    jsonschema.Draft202012Validator(schema).validate(rec)
    return {"code": code, "rec": rec, "stdout": so.getvalue(), "out": out}


def test_every_entry_says_what_was_asked_and_the_counts_add_up(audited):
    rec = audited["rec"]
    trajs = rec["outputs"]["trajectories"]
    assert [t["request"] for t in trajs if t["topic"] == "/joint_trajectory"] == ["execute"] * 4
    assert [t["request"] for t in trajs if t["topic"] == "/dyn_node/check_trajectory"] == ["check"] * 5
    assert [not t["feasible"] for t in trajs if t["request"] == "execute"] == list(EXECUTED)
    assert [not t["feasible"] for t in trajs if t["request"] == "check"] == list(QUESTIONS)
    assert rec["outputs"]["trajectory_counts"] == {
        "executed": 4, "executed_infeasible_or_rejected": 1, "questions": 5,
        "questions_infeasible_or_rejected": 2,
        "by_request": {"check": {"total": 5, "infeasible_or_rejected": 2},
                       "execute": {"total": 4, "infeasible_or_rejected": 1}}}
    assert rec["outputs"]["trajectories_infeasible_or_rejected"] == 1  # executed only, as before


def test_the_summary_line_adds_up(audited):
    """Not "1 of 9 trajectories infeasible or rejected": each count over its own total."""
    summary = audited["rec"]["verdict"]["summary"]
    assert summary.startswith("1 of 4 executed trajectories infeasible or rejected; "
                              "2 of 5 questions answered infeasible or rejected (check 5)")
    assert audited["stdout"].splitlines()[0] == "VIOLATIONS: " + summary
    assert audited["code"] == 1  # the executed infeasible one is the violation


def test_a_run_whose_only_no_is_a_question_is_feasible(tmp_path, capsys):
    bag = write_bag(tmp_path, BagSpec("asked", "panda", 1.0, trajectories=(False,), questions=(True,)))
    code = audit_main([str(bag), "--out", str(tmp_path / "o"), "--no-report"])
    first = capsys.readouterr().out.splitlines()[0]
    assert code == 0 and first.startswith("FEASIBLE: all feasible: 500 joint states, 1 executed trajectory; ")
    assert first.endswith("; 1 of 1 question answered infeasible or rejected (check 1)")


def test_the_report_table_has_the_request_and_both_counts(audited):
    page = (audited["out"] / "report.html").read_text()
    assert "<th>request</th>" in page
    rows = re.findall(r"<tr><td>(\d+)</td><td>(execute|check)</td><td class=\"num\">[^<]*</td>"
                      r"<td><span class='pill (ok|bad|warn)'>", page)
    assert len(rows) == 9
    # an executed "no" is a violation (red), a question's an answer (amber)
    assert {(r, p) for _i, r, p in rows} == {("execute", "bad"), ("execute", "ok"), ("check", "warn"),
                                            ("check", "ok")}
    assert sum(p == "warn" for *_x, p in rows) == 2 and sum(p == "bad" for *_x, p in rows) == 1
    assert "Executed: <b>1 of 4</b> infeasible or rejected" in page
    assert "<b>2 of 5</b> answered infeasible or rejected" in page


def test_a_new_question_kind_slots_in():
    """A retime service (or any new request role) counts as a question of its own kind."""
    t = RequestTally()
    for req, ok in (("execute", True), ("execute", False), ("check", False), ("retime", True),
                    ("inverse_dynamics", False)):
        t.add(req, answered_yes=ok)
    assert (t.executed, t.executed_bad, t.questions, t.questions_no) == (2, 1, 3, 2)
    assert t.sentence() == ("1 of 2 executed trajectories infeasible or rejected; 2 of 3 questions "
                            "answered infeasible or rejected (check 1, inverse_dynamics 1, retime 1)")
    assert request_of_role("joint_trajectory") == "execute"
    assert request_of_role("check_trajectory") == "check"
    assert request_of_role("retime_trajectory") != "execute"  # unknown roles are never executions


def test_gate_goals_are_executed_trajectories():
    """A gate goal is sent to be executed: counted with joint_trajectory's, never as a question;
    a rejected goal or one forwarded infeasible (check mode) is a "no", a retimed one is not."""
    from dyn_node.audit.replay.gates import executed_feasible

    recs = [{"decision": "forwarded", "feasible": True}, {"decision": "rejected", "feasible": False},
            {"decision": "rejected", "feasible": True},  # e.g. rejected for a NaN before any check
            {"decision": "forwarded", "feasible": False}, {"decision": "retimed", "feasible": False}]
    assert [executed_feasible(r) for r in recs] == [True, False, False, False, True]
    t = RequestTally()
    t.add("execute", answered_yes=True)
    t.add("check", answered_yes=False)
    for r in recs:
        t.add("gate_goal", answered_yes=executed_feasible(r))
    assert (t.executed, t.executed_bad, t.questions, t.questions_no) == (6, 3, 1, 1)
    assert t.to_dict()["by_request"]["gate_goal"] == {"total": 5, "infeasible_or_rejected": 3}
    assert t.sentence() == ("3 of 6 executed trajectories (5 gate goals) infeasible or rejected; "
                            "1 of 1 question answered infeasible or rejected (check 1)")
