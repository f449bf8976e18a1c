"""What the audit commands (dyn-audit, dyn-fleet) share on the command line: the audit options
(dyn-fleet applies dyn-audit's to every bag), and errors: input that cannot be used is one line
``PROG: error: ...`` on stderr and exit code 2, never a traceback; Ctrl-C is ``PROG: interrupted``
and 130 (128 + SIGINT, as a shell reports it)."""
from __future__ import annotations

import argparse
import sys
from typing import Callable, TypeVar

from dyn_node.errors import DynNodeError
from dyn_node.audit.exit_codes import EXIT_UNUSABLE

EXIT_INTERRUPTED = 130
R = TypeVar("R")


def add_audit_options(p: argparse.ArgumentParser, *, every_bag: bool = False) -> None:
    """--robot-description/--robot-model, --limits, --topics, --gap-threshold, --no-report: how a
    bag is audited (``every_bag``: dyn-fleet's wording, the same options for each bag)."""
    bag, urdf = ("each bag", "URDF") if every_bag else ("the bag", "FILE")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--robot-description", metavar=urdf, default="",
                     help=f"URDF file (overrides the description stored in {bag})")
    src.add_argument("--robot-model", metavar="NAME", default="",
                     help=f"built-in model: panda, ur5, planar_2link (overrides {bag})")
    p.add_argument("--limits", metavar="FILE", default="", help=f"joint limits YAML (overrides {bag}'s)")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                   help="only use these topics (roles by type and name: */joint_states, "
                        "*/joint_trajectory, node outputs)")
    p.add_argument("--gap-threshold", type=float, default=0.05, metavar="S",
                   help="report joint_states gaps longer than this (s, default 0.05)")
    p.add_argument("--no-report", action="store_true",
                   help="write evidence.json only" + (", no report.html per bag" if every_bag else ""))


def error_line(prog: str, exc: BaseException) -> str:
    """``PROG: error: ...``; an OSError as its reason and file (``No such file ...: /x``)."""
    if isinstance(exc, OSError):
        return f"{prog}: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": ")
    return f"{prog}: error: {exc}"


def run_command(prog: str, work: Callable[[], R], report: Callable[[R], int]) -> int:
    """``report(work())``, the exit code. A DynNodeError (every reportable input error: bag,
    audit, fleet, model, settings) or an OSError raised by ``work`` is reported in one line and
    gives exit 2; Ctrl-C gives 130. ``report`` runs outside: its own failures are not input's."""
    try:
        result = work()
    except (DynNodeError, OSError) as exc:
        print(error_line(prog, exc), file=sys.stderr)
        return EXIT_UNUSABLE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return report(result)


__all__ = ["EXIT_INTERRUPTED", "add_audit_options", "error_line", "run_command"]
