"""Markdown from bench.json: docs/BENCHMARKS.md, the summary in docs/performance.md and the terminal tables."""
from __future__ import annotations

import math
import re
from pathlib import Path

BEGIN, END = "<!-- BENCH:BEGIN -->", "<!-- BENCH:END -->"


def _f(x, digits: int = 3, unit: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, (int, float)):
        ax = abs(x)
        s = (f"{x:.{digits}g}" if ax < 10 ** digits else f"{x:,.0f}")
        return s + unit
    return str(x)


def _ratio(x, bold: bool = False) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return f"**{x:.2f}**" if bold else f"{x:.2f}"


def _pct(x) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{100 * x:.2f}%"


_COMPARISON_LABELS = {
    "p99_dyn_node_over_minimal_1k": "live: dyn_node p99 ÷ minimal node p99 at 1 kHz (target ≤ 1.0)",
    "p50_dyn_node_over_minimal_1k": "live: dyn_node p50 ÷ minimal node p50 at 1 kHz",
    "max_rate_dyn_node_over_minimal": "live: dyn_node highest no-loss rate ÷ minimal node's (— : the "
                                      "minimal node lost messages at every rate tried)",
    "p99_minimal_over_bare_1k": "live: minimal node p99 ÷ bare republisher p99 at 1 kHz",
    "recording_cpu_overhead_1k": "live: CPU added by recording, whole process (target ≤ 10%)",
    "recording_cpu_per_output_overhead_1k": "live: CPU added by recording, per output answered",
    "p99_contact_over_minimal_1k": "live: dyn_node with the contact observer (e) p99 ÷ minimal node "
                                   "p99 at 1 kHz (target ≤ 1.0)",
    "p99_contact_over_dyn_node_1k": "live: (e) p99 ÷ dyn_node (c) p99 at 1 kHz",
    "loss_contact_1k": "live: (e) ~/external_torque lost at 1 kHz (target 0)",
    "loss_contact_wrench_1k": "live: (e) ~/external_wrench lost at 1 kHz (target 0)",
}
#: comparisons that are fractions (shown as percentages)
_FRACTION_KEYS = ("overhead", "loss_")


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _status(sec: dict) -> str | None:
    st = sec.get("status")
    return None if st in (None, "ok") else st


def machine_md(doc: dict) -> str:
    m = doc["machine"]
    v = ", ".join(f"{k} {val}" for k, val in m["versions"].items())
    return (f"Machine: {m['cpu_model']}, {m['cpu_count']} cores ({m['cpus_usable']} usable), "
            f"{m['memory_gib']} GiB RAM, Linux {m['kernel']}.  \nVersions: {v}.")


def dynamics_md(sec: dict) -> str:
    if _status(sec):
        return f"Dynamics: {_status(sec)}"
    d = sec["result"]
    out = [f"Inverse dynamics τ = RNEA(q, q̇, q̈) on {d['n_batch']:,} seeded states per robot "
           f"(single-call timings over up to the first {d['n_call']:,}, fewer for calls slower than "
           f"0.1 ms); median of {d['repeats']} repeats, interleaved across implementations "
           "(PyKDL's in its own process). "
           f"{d['note']}. Every implementation was checked against dyn_node's batched result "
           f"before timing (tolerance {d['tolerance_Nm']:g} N·m); the last column is the largest "
           "difference found. ×loop: batch time ÷ the plain Python pinocchio.rnea loop's, "
           "same run (below 1 = faster)."]
    for robot in dict.fromkeys(r["robot"] for r in d["rows"]):
        rows = []
        for r in (r for r in d["rows"] if r["robot"] == robot):
            if r.get("status") != "ok":
                rows.append([r["impl"], r.get("what", ""), r["status"], "—", "—", "—", "—",
                             _f(r.get("max_abs_diff_Nm"), 2)])
                continue
            rows.append([r["impl"], r["what"], _f(r.get("per_call_us")),
                         _f(r.get("per_call_vs_pin_call"), 2), _f(r.get("batch_s", float("nan")) * 1e3),
                         _f(r.get("batch_per_state_us")), _f(r.get("batch_vs_pin_loop"), 2),
                         _f(r.get("max_abs_diff_Nm"), 2)])
        nv = next(r.get("nv") for r in d["rows"] if r["robot"] == robot)
        out.append(f"**{robot}** ({nv} DoF)\n\n" + _table(
            ["implementation", "what it measures", "per call (µs)", "×pin call",
             f"batch of {d['n_batch']:,} (ms)", "µs/state", "×loop", "max abs Δτ vs dyn_node (N·m)"], rows))
    return "\n\n".join(out)


def live_md(sec: dict) -> str:
    if _status(sec):
        return f"Live path: {_status(sec)}"
    d = sec["result"]
    rows = []
    for r in d["rows"]:
        if r.get("status") != "ok":
            rows.append([r["subject"], r["what"], r["status"]] + ["—"] * 7)
            continue
        steps = ", ".join(f"{w['achieved_hz']:.0f} Hz: {_pct(w['loss'])}" for w in r["windows"]
                          if w.get("step", True))
        rows.append([r["subject"], r["what"], _f(r["p50_us_1k"]), _f(r["p99_us_1k"]),
                     _f(r["cpu_share_1k"], 2), _f(r.get("cpu_us_per_output_1k")), _pct(r["loss_1k"]),
                     _f(r["max_rate_no_loss_hz"], 4) if r["max_rate_no_loss_hz"] else "none (loss at every rate tried)",
                     steps, _f(r.get("vm_hwm_mib"))])
    text = [f"7-DoF JointState from a separate publisher process, reliable QoS depth 10, over DDS on "
            f"localhost (ROS_DOMAIN_ID {d['domain']}). Latency: receipt of the subject's output "
            f"minus the input's header stamp (= its publish time), p50/p99 over all messages of "
            f"the 1 kHz windows ({d.get('repeats_1k', 1)} × {d['window_s']:g} s, median across "
            f"windows). CPU: the subject's utime+stime over the window ÷ wall time (1 = one core), and "
            f"÷ outputs received. Loss counts messages lost anywhere on publisher → subject → "
            f"probe (every hop is a reliable, depth-10 queue in the subjects). "
            f"Rates stepped {d['rates']} Hz ({d['window_s']:g} s each) until more than 1% was lost; "
            "the publisher's achieved rate is shown. Peak RSS: VmHWM at the end of the run.",
            _table(["subject", "what it is", "p50 @1 kHz (µs)", "p99 @1 kHz (µs)",
                    "CPU @1 kHz (cores)", "CPU per output (µs)", "loss @1 kHz", "highest rate, no loss (Hz)",
                    "steps (rate: loss)", "peak RSS (MiB)"], rows)]
    c = d.get("comparisons", {})
    lines = []
    if "p99_dyn_node_over_minimal_1k" in c:
        lines.append(f"- dyn_node p99 ÷ minimal node p99 at 1 kHz: **{c['p99_dyn_node_over_minimal_1k']:.2f}** "
                     "(target ≤ 1.0)")
        lines.append(f"- dyn_node p50 ÷ minimal node p50 at 1 kHz: {c['p50_dyn_node_over_minimal_1k']:.2f}")
        lines.append(f"- dyn_node highest no-loss rate ÷ minimal node's: "
                     f"{_ratio(c['max_rate_dyn_node_over_minimal'], True)} (target ≥ 1.0; — when "
                     "the minimal node lost messages at every rate tried)")
    else:
        lines.append("- dyn_node ÷ minimal node: not measured (dyn_node row not available)")
    if "p99_minimal_over_bare_1k" in c:
        lines.append(f"- minimal node p99 ÷ bare republisher p99 at 1 kHz: {c['p99_minimal_over_bare_1k']:.2f}")
    if "recording_cpu_overhead_1k" in c:
        by_pair = d.get("recording_cpu_overhead_1k_by_pair", [])
        how = (f", median of {len(by_pair)} runs of (c) and (d) one after the other: "
               + ", ".join(_pct(x) for x in by_pair)) if len(by_pair) > 1 else ""
        lines.append(f"- CPU added by recording at 1 kHz ((d) ÷ (c) − 1): "
                     f"**{_pct(c['recording_cpu_overhead_1k'])}** of process CPU, "
                     f"{_pct(c.get('recording_cpu_per_output_overhead_1k'))} per output answered "
                     f"(target ≤ 10%{how})")
    else:
        lines.append("- recording CPU overhead: not measured (row (c) or (d) not available)")
    lines.append(_contact_md(d))
    text.append("\n".join(lines))
    if d.get("detection"):
        text.append(_detection_md(d["detection"]))
    return "\n\n".join(text)


def _contact_md(d: dict) -> str:
    """Issue 19's cost lines: (e) against the minimal node in the same run, and its loss."""
    c = d.get("comparisons", {})
    if "p99_contact_over_minimal_1k" not in c:
        why = next((r["status"] for r in d["rows"] if r.get("key") == "dyn_node_contact"),
                   "row (e) not run")
        return f"- contact observer on ((e) ÷ minimal node): not measured ({why})"
    by_pair = d.get("p99_contact_over_minimal_1k_by_pair", [])
    how = (f"median of {len(by_pair)} runs of (b) fed the same efforts and (e) one after the "
           "other: " + ", ".join(f"{x:.2f}" for x in by_pair) + "; ") if len(by_pair) > 1 else ""
    return (f"- contact observer on: (e) p99 ÷ minimal node p99 at 1 kHz: "
            f"**{c['p99_contact_over_minimal_1k']:.2f}** ({how}target ≤ 1.0; (e) ÷ (c): "
            f"{_ratio(c.get('p99_contact_over_dyn_node_1k'))}); lost at 1 kHz: ~/external_torque "
            f"**{_pct(c['loss_contact_1k'])}**, ~/external_wrench "
            f"{_pct(c.get('loss_contact_wrench_1k'))} (the worst run; target none)")


def _detection_line(det: dict) -> str:
    if det.get("status") != "ok":
        return det.get("status", "")
    return (f"median {_f(det['median_ms'])} ms, p95 {_f(det['p95_ms'])} ms over "
            f"{det['detected']} of {det['pushes']} pushes; 1/K = {_f(det['one_over_k_ms'])} ms, "
            f"3/K = {_f(det['three_over_k_ms'])} ms")


def _detection_md(det: dict) -> str:
    head = ("Contact detection latency (issue 19): from the first sample a push moved (dyn_sim's "
            "MuJoCo simulator at 1 kHz) to the first `contact` state of the node's ContactMonitor "
            "fed every sample (no DDS: the rows above are the transport), measured by "
            "benchmarks/contact_bench.py")
    if det.get("status") != "ok":
        return f"{head}: {det.get('status')}"
    few = "" if det.get("enough", True) else " (fewer pushes than the 20 the figure needs)"
    return (f"{head}{': ' + det['what'] if det.get('what') else ''}.\n\n" + _table(
        ["pushes (detected / applied)", "force (N)", "median (ms)", "p95 (ms)", "max (ms)",
         "1/K (ms)", "3/K, 95 % rise (ms)", "contact_min_duration (ms, included)"],
        [[f"{det['detected']} / {det['pushes']}{few}", _f(det.get("force_n")),
          _f(det["median_ms"]), _f(det["p95_ms"]), _f(det["max_ms"]), _f(det["one_over_k_ms"]),
          _f(det["three_over_k_ms"]), _f(det.get("min_duration_ms"))]]))


def feasibility_md(sec: dict) -> str:
    if _status(sec):
        return f"Feasibility: {_status(sec)}"
    d = sec["result"]
    if "processes" in d:
        how = (f"each figure is the median over {d['processes']} fresh processes of that "
               f"process's median of {d['repeats']} interleaved rounds, and each ratio the "
               "median over those processes of the per-round ratios (the loop alone took "
               + ", ".join(f"{_f(t * 1e3)}" for t in d["rnea_loop_by_process_s"])
               + " ms in them; the check without the margin came to "
               + ", ".join(f"{r:.2f}×" for r in d["ratio_no_margin_by_process"]) + ")")
    else:
        how = f"median of {d['repeats']} repeats"
    return (f"A 10 s 7-DoF Panda trajectory ({d['n_points']} waypoints, {d['interpolation']}) "
            f"sampled at 1 ms ({d['n_samples']:,} samples), every limit kind set; {how}.\n\n"
            + _table(["what", "check_trajectory (ms)", "pinocchio.rnea loop, same samples (ms)",
                      "ratio", "target"], _feasibility_rows(d)))


def _feasibility_rows(d: dict) -> list[list[str]]:
    loop = d["rnea_loop_s"]

    def row(what: str, t: float, ratio: float | None = None, target: str = "",
            bold: bool = False) -> list[str]:
        r = f"{(t / loop if ratio is None else ratio):.2f}×"
        return [what, _f(t * 1e3), _f(loop * 1e3), f"**{r}**" if bold else r, target]

    rows = []
    if "check_no_margin_s" in d:   # figures from before this row existed have only the first
        rows.append(row(d["what"], d["check_s"], d["ratio"],
                        "(the margin is outside the targets' scope)"))
        rows.append(row(d["what_no_margin"], d["check_no_margin_s"], d["ratio_no_margin"],
                        "≤ 1.0× (issue 8), ≤ 1.5× (issue 4)", bold=True))
    else:
        rows.append(row(d["what"], d["check_s"], d["ratio"], "≤ 1.0× (issue 8), ≤ 1.5× (issue 4)",
                        True))
    rows += _task_rows(d.get("task"), row, loop)
    if "check_all_cores_s" in d:
        rows.append(row(d["what_all_cores"], d["check_all_cores_s"], d["ratio_all_cores"]))
        if "check_no_margin_all_cores_s" in d:
            rows.append(row(d["what_no_margin_all_cores"], d["check_no_margin_all_cores_s"],
                            d["ratio_no_margin_all_cores"]))
        r1 = d.get("ratio_passes", d["rnea_passes_s"] / loop)
        r2 = d.get("ratio_passes_all_cores", d["rnea_passes_all_cores_s"] / loop)
        rows.append([d["what_rnea_passes"],
                     f"{_f(d['rnea_passes_s'] * 1e3)} / {_f(d['rnea_passes_all_cores_s'] * 1e3)} "
                     f"({d['cores']} threads)", _f(loop * 1e3), f"{r1:.2f}× / {r2:.2f}×", ""])
    if "rnea_passes_no_margin_s" in d:
        rows.append(row(d["what_rnea_passes_no_margin"], d["rnea_passes_no_margin_s"],
                        d.get("ratio_passes_no_margin")))
    if "gravity_kernel_s" in d:
        rows.append(row(d["what_gravity"] + ": **kernel**", d["gravity_kernel_s"],
                        d["ratio_gravity_kernel"]))
        rows.append(row(d["what_gravity"] + ": **Pinocchio RNEA**", d["gravity_rnea_s"],
                        d["ratio_gravity_rnea"]))
    if "frame_kernels_s" in d:
        rows.append(row(d["what_frame_kernels"], d["frame_kernels_s"], d["ratio_frame_kernels"],
                        "a fraction of the 2.0× of issue 18"))
        rows.append(row(d["what_frame_kernels"] + ": **the two points' kinematics alone**",
                        d["frame_kinematics_s"], d["ratio_frame_kinematics"]))
    for mode, label in (("default", "glibc's defaults"), ("retain", "freed memory kept mapped")):
        h = d.get("heap", {}).get(mode)
        if h:
            rows.append([f"{d['what_heap']}: **{label}**, {h['faults']:,} minor page faults per "
                         "check", _f(h["check_s"] * 1e3), _f(h["loop_s"] * 1e3),
                         f"{h.get('ratio', h['check_s'] / h['loop_s']):.2f}×", ""])
    return rows


def _task_rows(t: dict | None, row, loop: float) -> list[list[str]]:
    """Issue 18's rows: every joint kind and every task kind configured."""
    if not t:
        return []
    target = "≤ 2.0× (issue 18)"
    if t.get("status") != "ok":
        return [[t["what"], t["status"], _f(loop * 1e3), "—", target]]
    by = ", ".join(f"{r:.2f}×" for r in t["ratio_no_margin_by_process"])
    w = t["worst_task"]
    return [row(f"{t['what']}, without the payload margin (by process: {by}; the joint kinds "
                f"alone {t['joint_kinds_ratio_no_margin']:.2f}× in the same rounds; worst task "
                f"kind {w['kind']} at {w['place']} {w['ratio']:.2f} of its limit)",
                t["check_no_margin_s"], t["ratio_no_margin"], target, bold=True),
            row(f"{t['what']}, with the payload margin", t["check_s"], t["ratio"])]


def recording_md(sec: dict) -> str:
    if _status(sec):
        return f"Recording and audit: {_status(sec)}"
    d = sec["result"]
    w = d["writer"]
    out = [f"Writer ceiling: {w['n_messages']:,} serialized 7-DoF JointStates, median of "
           f"{w['repeats']} interleaved repeats.\n\n" + _table(
               ["what", "dyn_node Recorder (msgs/s)", "raw mcap Writer (msgs/s)", "ratio"],
               [[w["what"], _f(w["recorder_msgs_per_s"], 4), _f(w["raw_mcap_msgs_per_s"], 4),
                 f"{w['ratio']:.2f}"]])]
    a = d.get("audit", {})
    if a:
        head = (f"Audit: a {a['bag_seconds']:g} s 1 kHz 7-DoF bag ({a['bag_messages']:,} messages, "
                f"{a['bag_mib']:.1f} MiB, written with dyn_node's Recorder). Raw read = mcap's reader "
                "iterating every message (decompressed, not decoded).")
        if a.get("status") != "ok":
            out.append(head + f"\n\nRaw read: {_f(a['raw_read_msgs_per_s'], 4)} msgs/s. dyn-audit: {a['status']}")
        else:
            rss = ", ".join(f"{k} bag: {_f(v)} MiB" for k, v in a["peak_rss_mib"].items())
            out.append(head + "\n\n" + _table(
                ["what", "msgs/s", "÷ raw read", "target"],
                [["mcap reader alone", _f(a["raw_read_msgs_per_s"], 4), "1", ""],
                 [f"dyn-audit end to end (process start to exit, {_f(a['audit_wall_s'])} s, "
                  f"median of {a.get('audit_repeats', 1)})",
                  _f(a["audit_msgs_per_s_end_to_end"], 4), _ratio(a["ratio_end_to_end"], True), "≥ 0.30"],
                 [f"dyn-audit marginal (Δmessages ÷ Δtime vs a {a.get('small_bag_seconds', 1):g} s bag)",
                  _f(a["audit_msgs_per_s_marginal"], 4), _ratio(a["ratio_marginal"]), "≥ 0.30"]])
                + f"\n\nPeak RSS of dyn-audit (VmHWM/ru_maxrss): {rss}; the {a['huge_bag_seconds']:g} s "
                  f"bag is {a['huge_bag_mib']:.0f} MiB and "
                  + (f"took {_f(a['huge_bag_wall_s'])} s." if a.get("huge_bag_finished", True)
                     else f"its audit was stopped after {_f(a['huge_bag_wall_s'])} s (did not finish)."))
    return "\n\n".join(out)


def fleet_md(sec: dict) -> str:
    if _status(sec):
        return f"Fleet: {_status(sec)}"
    d = sec["result"]
    rows = [[f"{r['workers']} worker(s)", _f(r["bags_per_s"]), _f(r["msgs_per_s"], 4),
             _f(r["cold_bags_per_s"]), _f(r["ray_start_s"]), _f(r["per_bag_overhead_s"] * 1e3),
             _f(r["mean_task_s"] * 1e3)] for r in d["rows"]]
    rss = d["rss"]
    return (f"dyn-fleet on local Ray: {d['n_bags']} Panda bags of {d['bag_seconds']:g} s at 1 kHz "
            f"({d['n_messages']:,} messages), every bag one task (audit + report). Rates are the "
            "median of three passes on the same engine after the first (workers reused); cold = "
            "the first pass, which starts the worker processes. Task per bag = time inside the "
            "task (hash, audit, report); it rises with 2 workers when the cores are shared.\n\n"
            + _table(["engine", "bags/s", "msgs/s", "cold bags/s", "Ray start (s)",
                      "Ray overhead per bag (ms)", "task per bag (ms)"], rows)
            + f"\n\nScaling efficiency (2-worker rate ÷ 2 × 1-worker rate): "
              f"**{d['scaling_efficiency']:.2f}** (target ≥ 0.8). Peak RSS of one worker: "
              f"{_f(rss['hwm_after_short_mib'])} MiB after {rss['bags_each']} bags of "
              f"{rss['short_s']:g} s, {_f(rss['hwm_after_long_mib'])} MiB after {rss['bags_each']} more "
              f"of {rss['long_s']:g} s (**{_pct(rss['growth'])}**, target ≤ 10 %).")


def _latency_table(what: str, rows: list[tuple[str, dict]]) -> str:
    """One row per subject: median, p99 and min of its latencies (ms)."""
    return _table([what, "median (ms)", "p99 (ms)", "min (ms)"],
                  [[name, _f(s["median_ms"]), _f(s["p99_ms"]), _f(s["min_ms"])] for name, s in rows])


def services_md(sec: dict) -> str:
    if _status(sec):
        return f"Services: {_status(sec)}"
    d = sec["result"]
    c, f = d["check"], d["floor"]
    return (f"Round trip of a `~/check_trajectory` call ({d['points']}-point {d['joints']}-DoF Panda "
            f"trajectory, {d['calls']} calls one at a time) from a client in another process, against "
            "a bare rclpy service of the same type that returns an empty response at once (the "
            "floor: the ROS round trip itself), interleaved in blocks in the same run.\n\n"
            + _latency_table("service", [("dyn_node ~/check_trajectory", c),
                                         ("bare rclpy service, empty response", f)])
            + f"\n\nRatio to the floor: median **{d['ratio_median']:.2f}×**, p99 {d['ratio_p99']:.2f}×. "
              f"The check itself (`on_demand.check` on the same trajectory, in one process) takes "
              f"{_f(d.get('core_check_ms'))} ms of the median.")


def gate_md(sec: dict) -> str:
    if _status(sec):
        return f"Gate: {_status(sec)}"
    d = sec["result"]
    g, p = d["gate"], d["proxy"]
    return (f"Latency from a client's `send_goal` to the downstream server's goal callback for a "
            f"{d['points']}-point {d['joints']}-DoF Panda FollowJointTrajectory goal ({d['goals']} goals "
            "one at a time, each checked and forwarded), through dyn_node's gate against a bare rclpy "
            "action proxy that forwards without checking, interleaved in blocks in the same run.\n\n"
            + _latency_table("path", [("dyn_node gate (reject mode)", g), ("bare action proxy", p)])
            + f"\n\nAdded by the gate: median **{_f(d['added_median_ms'])} ms**, p99 {_f(d['added_p99_ms'])} ms; "
              f"its check alone (the decision on the same goal, in one process) {_f(d['check_ms'])} ms"
              + (f", in the gate (its records' `check_time_s`) median {_f(d['gate_check']['median_ms'])} ms. "
                 f"Gate time − its check time, per goal: median {_f(d['gate_minus_check']['median_ms'])} ms, "
                 f"p99 **{_f(d['gate_minus_check']['p99_ms'])} ms**. Targets (adds ≤ check + 2 ms at the median; "
                 f"p99 of gate − check ≤ 10 ms): {'met' if d['target_met'] else 'NOT met'}.\n\n"
                 f"`retime` mode (every goal retimed, {d['retime_goals']} goals): send_goal → controller median "
                 f"{_f(d['retime']['median_ms'])} ms, p99 {_f(d['retime']['p99_ms'])} ms; the retiming itself "
                 f"median {_f(d['retime_check']['median_ms'])} ms, p99 {_f(d['retime_check']['p99_ms'])} ms."
                 if "gate_minus_check" in d else
                 f". Target (check + 2 ms at the median): {'met' if d['target_met'] else 'NOT met'}."))


def memory_md(doc: dict) -> str:
    rows = []
    live = doc["sections"].get("live", {})
    for r in live.get("result", {}).get("rows", []):
        rows.append([f"{r['subject']} at steady state (VmHWM after the live run)",
                     _f(r.get("vm_hwm_mib")) if r.get("status") == "ok" else r.get("status", "—")])
    rec = doc["sections"].get("recording", {}).get("result", {}).get("audit", {})
    for k, v in rec.get("peak_rss_mib", {}).items():
        rows.append([f"dyn-audit on the {k} bag", _f(v)])
    if not rows:
        return "Memory: not measured (live and recording sections not run)"
    return _table(["process", "peak RSS (MiB)"], rows)


def parsing_md(sec: dict) -> str:
    if _status(sec):
        return f"Parsing: {_status(sec)}"
    d = sec["result"]
    rows = [[r["format"], f"{r['bytes'] / 1e6:.1f}", _f(r["read_s"]), _f(r["vm_hwm_mib"])]
            if r.get("status") == "ok" else [r["format"], "—", r.get("status", "—"), "—"]
            for r in d["rows"]]
    return (f"`read_trajectory` of a {d['n_points']:,}-point, {d['joints']}-joint trajectory "
            "(positions, velocities, accelerations), each format in a fresh process; median of "
            f"{d['repeats']} reads, peak RSS of that process.\n\n"
            + _table(["format", "file (MB)", "read (s)", "peak RSS (MiB)"], rows))


def retime_md(sec: dict) -> str:
    from .retime_bench import render_md
    return _status(sec) or render_md(sec["result"])


def sim_md(sec: dict) -> str:
    from .sim_bench import render_md
    return _status(sec) or render_md(sec["result"])


SECTIONS = [("dynamics", "Dynamics", dynamics_md), ("live", "Live path", live_md),
            ("feasibility", "Feasibility check", feasibility_md),
            ("recording", "Recording and audit", recording_md), ("fleet", "Fleet (dyn-fleet on Ray)", fleet_md),
            ("services", "Question services", services_md),
            ("parsing", "Parsing trajectory files", parsing_md),
            ("retime", "Retiming (dyn_node.retime)", retime_md),
            ("gate", "FollowJointTrajectory gate", gate_md),
            ("sim", "Simulator (dyn_sim's controller panel)", sim_md)]


def render(doc: dict) -> str:
    parts = ["# Benchmarks", "",
             "Generated by `make bench` (`python -m benchmarks.run`) from `bench_out/bench.json`; "
             "do not edit by hand. Every figure is a median over repeats and every ratio is taken "
             "between figures measured in the same run of that section.", "",
             machine_md(doc)]
    for key, title, fn in SECTIONS:
        sec = doc["sections"].get(key)
        parts += ["", f"## {title}", ""]
        if sec is None:
            parts.append("Not run yet.")
            continue
        parts.append(f"_Measured {sec['measured_at']} ({'SMOKE (sizes too small to mean anything)' if sec.get('smoke') else 'quick' if sec.get('quick') else 'full'} run, "
                     f"{sec['wall_s']:.0f} s; 1-min load average {sec.get('loadavg_start', float('nan')):.1f} "
                     f"at start, {sec.get('loadavg_end', float('nan')):.1f} at end: other processes "
                     "on the machine share its cores)._")
        parts += ["", fn(sec)]
    parts += ["", "## Memory", "", memory_md(doc), ""]
    return "\n".join(parts)


def summary_md(doc: dict, *, full_page: str = "BENCHMARKS.md") -> str:
    """The short version for the summary page, between the BENCH markers; ``full_page`` is the
    generated page's path relative to the summary page's directory (its link must resolve)."""
    lines = [machine_md(doc), ""]
    rows = []
    dyn = doc["sections"].get("dynamics", {}).get("result")
    if dyn:
        for r in dyn["rows"]:
            if r["robot"] == "panda" and r.get("status") == "ok" and "batch_s" in r:
                rows.append([f"Panda, {dyn['n_batch']:,} states: {r['impl']}",
                             f"{_f(r['batch_s'] * 1e3)} ms ({_f(r['batch_vs_pin_loop'], 2)}× the Python pinocchio loop)"])
    live = doc["sections"].get("live", {}).get("result")
    if live:
        for r in live["rows"]:
            held = (f"no loss up to {_f(r['max_rate_no_loss_hz'], 4)} Hz" if r.get("max_rate_no_loss_hz")
                    else "lost messages at every rate tried")
            rows.append([f"live @1 kHz: {r['subject']}",
                         f"p50 {_f(r['p50_us_1k'])} µs, p99 {_f(r['p99_us_1k'])} µs, CPU "
                         f"{_f(r['cpu_share_1k'], 2)} cores, {held}"
                         if r.get("status") == "ok" else r["status"]])
        for k, v in live.get("comparisons", {}).items():
            # the recording overheads are fractions of the process CPU: shown as percentages
            rows.append([_COMPARISON_LABELS.get(k, k),
                         _pct(v) if any(f in k for f in _FRACTION_KEYS) else _ratio(v)])
        det = live.get("detection")
        if det:
            rows.append(["live: contact detection latency (simulated push → first `contact`)",
                         _detection_line(det)])
            if (pr := det.get("press")) and "settled_error_n" in pr:
                rows.append(["live: press on dyn_sim's table (issue 32): ContactMonitor vs ~/contact_truth",
                             f"first touch → `contact` {_f(pr['touch_to_contact_ms'])} ms; settled error "
                             f"{_f(pr['settled_error_n'])} N of {_f(pr['settled_force_n'])} N"])
    feas = doc["sections"].get("feasibility", {})
    if feas.get("result"):
        f = feas["result"]
        rows.append(["feasibility, 10,000 samples, with payload margin", f"{_f(f['check_s'] * 1e3)} ms = {f['ratio']:.2f}× a pinocchio.rnea loop"])
        if "check_no_margin_s" in f:
            rows.append(["feasibility, 10,000 samples, every limit kind + time scale (targets ≤ 1.0× / ≤ 1.5×)",
                         f"{_f(f['check_no_margin_s'] * 1e3)} ms = {f['ratio_no_margin']:.2f}× the loop; "
                         f"its torque passes alone "
                         f"{f.get('ratio_passes_no_margin', f['rnea_passes_no_margin_s'] / f['rnea_loop_s']):.2f}×"])
        t = f.get("task")
        if t:
            rows.append(["feasibility, 10,000 samples, every joint kind + every force/energy/"
                         "contact kind (target ≤ 2.0×)",
                         f"{_f(t['check_no_margin_s'] * 1e3)} ms = {t['ratio_no_margin']:.2f}× "
                         "the loop" if t.get("status") == "ok" else t["status"]])
    elif feas:
        rows.append(["feasibility", feas.get("status", "")])
    rec = doc["sections"].get("recording", {})
    if rec.get("result"):
        w = rec["result"]["writer"]
        rows.append(["recorder ceiling", f"{_f(w['recorder_msgs_per_s'], 4)} msgs/s ({w['ratio']:.2f}× raw mcap)"])
        a = rec["result"].get("audit", {})
        if a.get("status") == "ok":
            rows.append(["dyn-audit throughput", f"{_f(a['audit_msgs_per_s_end_to_end'], 4)} msgs/s "
                         f"({a['ratio_end_to_end']:.2f}× raw mcap read)"])
        elif a:
            rows.append(["dyn-audit", a.get("status", "")])
    elif rec:
        rows.append(["recording", rec.get("status", "")])
    fl = doc["sections"].get("fleet", {})
    if fl.get("result"):
        f = fl["result"]
        two = f["rows"][-1]
        rows.append(["dyn-fleet, 2 workers", f"{_f(two['bags_per_s'])} bags/s, {_f(two['msgs_per_s'], 4)} msgs/s; "
                     f"scaling efficiency {f['scaling_efficiency']:.2f}; Ray start {_f(f['ray_start_s'])} s"])
    elif fl:
        rows.append(["fleet", fl.get("status", "")])
    gate = doc["sections"].get("gate", {})
    if gate.get("result"):
        g = gate["result"]
        rows.append([f"FollowJointTrajectory gate, {g['points']}-point goal: send_goal → controller",
                     f"median {_f(g['gate']['median_ms'])} ms vs {_f(g['proxy']['median_ms'])} ms through a "
                     f"bare action proxy (adds {_f(g['added_median_ms'])} ms; its check {_f(g['check_ms'])} ms)"])
    elif gate:
        rows.append(["gate", gate.get("status", "")])
    lines.append(_table(["measured", "result"], rows))
    lines += ["", "Full tables, what each row measures, and the raw figures: "
              f"[{full_page}]({full_page}), `bench_out/bench.json`."]
    return "\n".join(lines)


def replace_between_markers(path: Path, body: str) -> bool:
    """Replace the text between the BENCH markers in ``path``; False if the file or markers are absent."""
    if not path.exists():
        return False
    text = path.read_text()
    pattern = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.S)
    if not pattern.search(text):
        return False
    new = pattern.sub(lambda _m: f"{BEGIN}\n{body}\n{END}", text, count=1)
    if new != text:
        path.write_text(new)
    return True
