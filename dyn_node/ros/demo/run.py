"""What the scenes of one demo run share (DemoRun) and how they print."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from dyn_node.ros.demo.processes import Child
from dyn_node.ros.demo.stack import Stack
from dyn_node.ros.demo.summary import Outcome


def say(s: str) -> None:
    print(s, flush=True)


def banner(title: str) -> None:
    say("=" * 100)
    say(f"dyn_node demo — {title}")
    say("=" * 100)


@dataclass
class DemoRun:
    """What the scenes of one demo run share: where it writes, the children's environment, and
    what has been observed and checked so far."""

    out: Path
    t_begin: float
    env: dict[str, str] = field(default_factory=dict)
    children: list[Child] = field(default_factory=list)
    stack: Stack | None = None
    outcomes: list[Outcome] = field(default_factory=list)
    checks: list[tuple[bool, str]] = field(default_factory=list)
    unavailable: list[str] = field(default_factory=list)
    bag_path: str | None = None
    task_checks: list[tuple[bool, str]] = field(default_factory=list)  # the task-limits scene's
    extra_verdicts: int = 0  # ~/feasibility answers of the scenes beyond the three trajectories
    # the stamps of the scenes' trajectories on joint_trajectory: their ~/feasibility verdicts
    # are counted once, before the recording stops (a loaded machine delivers some late)
    verdict_stamps: list[int] = field(default_factory=list)
    push_checks: list[tuple[bool, str]] = field(default_factory=list)  # the push scene's
    retime_checks: list[tuple[bool, str]] = field(default_factory=list)  # ros/demo/retime.py

    @property
    def logs(self) -> Path:
        return self.out / "logs"

    @property
    def bag_dir(self) -> Path:
        return self.out / "bags"

    def elapsed(self) -> float:
        return time.monotonic() - self.t_begin

    def missing(self, what: str, say_text: str | None = None) -> None:
        """A stage that could not run: listed in the summary, and said now."""
        self.unavailable.append(what)
        say(say_text or f"stage unavailable: {what}")
