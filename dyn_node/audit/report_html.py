"""HTML pieces shared by the audit report, the trajectory-file report and fleet.html: escaping,
numbers, tables, embedded images, and the trajectories table (executed and questions apart)."""
from __future__ import annotations

import base64
import html
from typing import Any, Sequence

from dyn_node.audit.accounting import counts_of, is_executed, request_of


def _e(x: Any) -> str:
    return html.escape("" if x is None else str(x))


def _num(x: Any, fmt: str = "{:.4g}") -> str:
    if x is None:
        return "—"
    if isinstance(x, str):
        return "∞" if x == "inf" else ("−∞" if x == "-inf" else _e(x))
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, float)):
        return fmt.format(x) if isinstance(x, float) else str(x)
    return _e(x)


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _table(head: Sequence[str], rows: list[Sequence[str]], num_cols: Sequence[int] = ()) -> str:
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for r in rows:
        out.append("<tr>" + "".join(f'<td class="num">{c}</td>' if i in num_cols else f"<td>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _verdict_pill(t: dict) -> str:
    if t["feasible"]:
        return "<span class='pill ok'>feasible</span>"
    word = "infeasible" if t["accepted"] else "rejected"
    # a question's "no" is an answer (amber), an executed trajectory's a violation (red)
    return f"<span class='pill {'bad' if is_executed(t) else 'warn'}'>{word}</span>"


def _services_table(questions: dict) -> list[str]:
    """The question services' answers per service (their pairs are re-checked, not listed)."""
    if not questions:
        return []
    rows = [[_e(kind), str(q.get("answered", 0)), str(q.get("accepted", 0)), str(q.get("feasible", 0)),
             str(q.get("infeasible", 0)),
             _e(", ".join(f"{r or '?'} {n}" for r, n in sorted((q.get("not_accepted") or {}).items())))]
            for kind, q in sorted(questions.items())]
    return [_table(["service question", "answered", "accepted", "feasible", "infeasible",
                    "not accepted (reason)"], rows, (1, 2, 3, 4))]


def trajectories_section(out: dict, images: dict[str, bytes]) -> list[str]:
    """One row per trajectory with what was asked (execute, or the question's kind) and its
    verdict pill; the counts of both apart; the time-scale/payload plot."""
    p = ["<h2 id='trajectories'>Trajectories</h2>"]
    trajs = out["trajectories"]
    c = counts_of(out)
    if not trajs and not c["questions"]:
        return p + ["<p>No trajectories in the input.</p>"]
    p.append(f"<p>Executed: <b>{c['executed_bad']} of {c['executed']}</b> infeasible or rejected "
             f"(violations of the run). Questions (check, retime, inverse dynamics; request topics "
             f"and services): <b>{c['questions_no']} of {c['questions']}</b> answered infeasible or "
             "rejected (answers, not violations).</p>")
    p += _services_table(out.get("questions") or {})
    if not trajs:
        return p
    rows = [[str(t["index"]), _e(request_of(t)), _num(t["time_s"], "{:.3f}"), _verdict_pill(t),
             _num(t.get("time_scale")), _num(t.get("payload_margin_kg")), _e(t.get("worst_joint")),
             _e(t.get("worst_constraint")), _num(t.get("worst_ratio")), _num(t.get("n_points")),
             _num(t.get("duration_s")), _e(t.get("message"))] for t in trajs]
    p.append(_table(["#", "request", "at t (s)", "verdict", "time scale k", "payload margin (kg)",
                     "worst joint", "constraint", "worst ratio", "points", "duration (s)", "message"],
                    rows, (2, 4, 5, 8, 9, 10)))
    if "trajectories.png" in images:
        p.append(_img(images["trajectories.png"], "time scale and payload margin per trajectory"))
    return p
