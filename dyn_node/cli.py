"""What the audit commands (dyn-audit, dyn-fleet) share on the command line: input that cannot be
used is one line ``PROG: error: ...`` on stderr and exit code 2, never a traceback; Ctrl-C is
``PROG: interrupted`` and 130 (128 + SIGINT, as a shell reports it)."""
from __future__ import annotations

import sys
from typing import Callable, TypeVar

from .errors import DynNodeError
from .exit_codes import EXIT_UNUSABLE

EXIT_INTERRUPTED = 130
R = TypeVar("R")


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


__all__ = ["EXIT_INTERRUPTED", "error_line", "run_command"]
