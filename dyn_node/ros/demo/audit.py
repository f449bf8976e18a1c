"""Scene 5: dyn-audit on the bag dyn_node recorded, checked against the live verdicts."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_VIOLATIONS
from dyn_node.ros.demo.output import before_model_in_bag, unanswered_reason
from dyn_node.ros.demo.processes import Child, module_available
from dyn_node.ros.demo.run import DemoRun, say
from dyn_node.ros.demo.stack import check_interrupted


def scene_audit(run: DemoRun) -> None:
    """5. dyn-audit on the bag dyn_node recorded, checked against the live verdicts."""
    bags = sorted(run.bag_dir.rglob("*.mcap")) if run.bag_dir.exists() else []
    if run.bag_path is None and bags:
        run.bag_path = str(bags[-1])
    say("")
    if not run.bag_path:
        run.missing("recording (no bag written)", "stage unavailable: recording (no bag was written)")
        return
    bag = Path(run.bag_path)
    say(f"bag: {bag}")
    if not module_available("dyn_node.audit.bag_audit"):
        run.missing("dyn-audit (module dyn_node.audit.bag_audit missing)")
        return
    audit_dir = run.out / "audit"
    say(f"running dyn-audit on the bag → {audit_dir} …")
    a = Child("dyn-audit", [sys.executable, "-m", "dyn_node.audit.bag_audit", str(bag), "--out",
                            str(audit_dir)], run.env, run.logs / "dyn_audit.log")
    rc = _wait_for(a, 90)
    say("\n".join("  " + ln for ln in a.tail(15).splitlines()))
    report = audit_dir / "report.html"
    evidence = audit_dir / "evidence.json"
    outcome = audit_outcome(rc, report.exists())
    if outcome == "partial":
        run.checks.append((False, f"dyn-audit: partial (exit 3): parts of the demo's own bag "
                                  f"could not be read (see {evidence}, "
                                  "input_quality.unreadable_ranges)"))
        say(f"  [FAIL] {run.checks[-1][1]}")
        say(f"report: {report}")
    elif outcome == "audited":
        for line in audit_recheck_lines(evidence, before_model_in_bag(bag)):
            say(line)
        live = sum(o.verdict_source == "dyn_node" for o in run.outcomes) + sum(
            o.check_feasible is not None for o in run.outcomes) + run.extra_verdicts  # check-only verdicts too
        check = audit_check(evidence, live)
        run.checks.append(check)
        say(f"  [{'PASS' if check[0] else 'FAIL'}] {check[1]}")
        say(f"report: {report}")
    else:
        run.missing(f"dyn-audit (exit {rc}; see {a.log_path})",
                    f"stage failed: dyn-audit exited {rc} (log {a.log_path})")


def _wait_for(child: Child, timeout_s: float) -> int:
    """The child's exit code once it ends, or once it was stopped after ``timeout_s``."""
    try:
        deadline = time.monotonic() + timeout_s
        while child.alive() and time.monotonic() < deadline:
            check_interrupted()
            try:
                child.proc.wait(timeout=0.1)
            except subprocess.TimeoutExpired:
                pass
        if child.alive():
            say(f"  {child.name} did not finish within {timeout_s:g} s")
    finally:
        rc = child.stop()
    return rc



def audit_outcome(rc: int, report_written: bool) -> str:
    """What the demo makes of dyn-audit's exit code: ``audited`` for 0 (all feasible) or 1
    (violations found: expected, the aggressive trajectory is infeasible); ``partial`` for 3
    (parts of the bag unreadable, no violations in the rest): the demo records its own bag, which
    must be whole, so that is a failure of the demo (a FAIL check), not a missing stage;
    ``failed`` for 2 (unusable input), anything else, or no report."""
    if not report_written:
        return "failed"
    return {EXIT_OK: "audited", EXIT_VIOLATIONS: "audited", EXIT_PARTIAL: "partial"}.get(rc, "failed")


def audit_recheck_lines(evidence: Path, before_model: int | None = None) -> list[str]:
    """One line per output topic the audit recomputed from the bag: matched and identical?
    ``before_model``: the node's count of inputs taken before its model (why some went
    unanswered, output.unanswered_reason)."""
    try:
        rec = json.loads(evidence.read_text())
        recheck = rec.get("outputs", {}).get("recheck", {})
    except (OSError, ValueError, AttributeError) as exc:
        return [f"  (could not read {evidence}: {exc})"]
    lines = ["dyn-audit recomputed the live outputs from the bag alone:"]
    for topic, d in sorted(recheck.items()):
        lines.append(f"  {topic:<36} matched {d.get('matched')}, unmatched {d.get('unmatched')}, "
                     f"not answered live {d.get('unanswered', 0)}"
                     f"{unanswered_reason(d.get('unanswered', 0), before_model)}, "
                     f"max |difference| {d.get('max_abs_difference')}, identical {d.get('identical')}")
    return lines


def audit_check(evidence: Path, live_verdicts: int) -> tuple[bool, str]:
    """dyn-audit reproduced every live ~/feasibility verdict from the bag, identically."""
    try:
        recheck = json.loads(evidence.read_text())["outputs"]["recheck"]
        # executions' verdicts on ~/feasibility, the questions' in ~/check_trajectory's events
        rows = [v for k, v in recheck.items() if k.endswith(("feasibility", "check_trajectory/_service_event"))]
        if not rows:
            raise KeyError("feasibility")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return False, f"dyn-audit: no feasibility recheck in {evidence} ({exc!r})"
    matched = sum(d.get("matched", 0) for d in rows)
    identical = all(d.get("identical") for d in rows if d.get("matched"))
    ok = matched == live_verdicts and not any(d.get("unmatched") for d in rows) and identical
    return ok, (f"dyn-audit reproduced the live verdicts from the bag: {matched} of "
                f"{live_verdicts} matched, identical {identical}")
