"""dyn-audit: replay a bag through the node's own core and write an EvidenceRecord and a report.

The bag is streamed (constant memory) through the same Monitor, ControllerTracker and
check_trajectory the node runs, and the node's recorded outputs are recomputed and compared.
Usage, outputs and exit codes: docs/audit.md; batch replay and configuration changes:
docs/BAGS.md.
"""
from __future__ import annotations

import argparse
import gc
import sys
from functools import partial
from typing import Sequence

from dyn_node import __version__
from dyn_node.audit.cli import add_audit_options, run_command
# The stages live in audit.pipeline, audit.sections and audit.replay.*; their names stay importable
# from here for the scripts, tests and benchmarks written against dyn_node.audit.bag_audit.
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS, exit_code  # noqa: F401
from dyn_node.audit.options import AuditError, AuditOptions, AuditResult  # noqa: F401
from dyn_node.audit.pipeline import Audit, run_audit, stream  # noqa: F401
from dyn_node.audit.replay.config import (AuditSource, model_differences, open_bag,  # noqa: F401
                                          parameters_from_yaml, task_limits_differences)
from dyn_node.audit.replay.inputs import Replay, ReplayResult  # noqa: F401
from dyn_node.audit.replay.recheck import RecheckResult, Rechecker  # noqa: F401
from dyn_node.audit.replay.roles import ROLE_FEAS, ROLE_GRAVITY, ROLE_ID, ROLE_JOINT_STATES, Roles  # noqa: F401
from dyn_node.audit.replay.stats import Episodes, Histogram, LiveStats  # noqa: F401
from dyn_node.audit.sections import add_verdict, build_evidence  # noqa: F401
from dyn_node.core.live.allocator import retain_freed_memory


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dyn-audit", description="Replay a bag through dyn_node's core; write evidence.json and "
        "report.html. Exit 0: all feasible, 1: violations found, 2: unusable input, "
        "3: partial (parts of the bag unreadable, no violations in the rest).")
    p.add_argument("bag", help="bag directory (rosbag2 layout), or a single .mcap file")
    p.add_argument("--out", metavar="DIR", default="audit", help="output directory (default: ./audit)")
    add_audit_options(p)
    p.add_argument("--version", action="version", version=f"dyn-audit {__version__}")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The command; ``argv`` None: the process's own command line, which ends when this returns."""
    args = build_parser().parse_args(argv)
    retain_freed_memory()     # each trajectory re-checked reuses the last one's pages
    opts = AuditOptions(bag=args.bag, robot_description=args.robot_description,
                        robot_model=args.robot_model, limits=args.limits, out=args.out,
                        topics=tuple(args.topics), gap_threshold_s=args.gap_threshold,
                        report=not args.no_report)
    # A process of its own keeps what is alive now (modules, compiled kernels) to the end: frozen,
    # no collection walks it, and the exit's collection skips the run's too (Numba's objects
    # took 0.1-0.15 s to tear down). Called in-process (argv given), the caller's heap is left alone.
    own_process = argv is None
    if own_process:
        gc.freeze()
    code = run_command("dyn-audit", partial(run_audit, opts), partial(_print_result, opts))
    if own_process:
        gc.freeze()
    return code


def _print_result(opts: AuditOptions, res: AuditResult) -> int:
    v = res.record["verdict"]
    print(f"{v['result'].upper()}: {v['summary']}")
    for f in v.get("findings", []):
        print(f"  - {f}")
    print(f"evidence: {res.out_dir / 'evidence.json'}")
    if opts.report:
        print(f"report:   {res.out_dir / 'report.html'}")
    return res.exit_code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
