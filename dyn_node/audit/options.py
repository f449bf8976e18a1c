"""dyn-audit's options, result and error: what the command line, the fleet and the stages share."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from dyn_node.errors import STATE_ERROR, DynNodeError

if TYPE_CHECKING:
    from dyn_node.core.robot.model_source import ModelCache


class AuditError(DynNodeError):
    """The audit cannot run: unusable bag or no model."""

    failure_label = STATE_ERROR


@dataclass(frozen=True)
class AuditOptions:
    bag: str
    robot_description: str = ""     # URDF file path (overrides the bag)
    robot_model: str = ""           # built-in model name (overrides the bag)
    limits: str = ""                # limits YAML (overrides the bag's limits_file)
    out: str = "audit"
    topics: tuple[str, ...] = ()
    gap_threshold_s: float = 0.05
    progress: bool | None = None    # None: only when stderr is a terminal
    report: bool = True
    # 2: the contact pass beside the replay and two plots at once; 1 in a fleet worker, whose
    # parallelism is the workers (a thread more per worker took the other workers' cores)
    threads: int = 2
    # models built earlier in this process (a fleet worker's); None (dyn-audit): built per bag
    model_cache: "ModelCache | None" = field(default=None, compare=False, repr=False)


@dataclass
class AuditResult:
    record: dict
    exit_code: int
    out_dir: Path
    files: list[Path] = field(default_factory=list)
    messages: int = 0
    wall_s: float = 0.0
