"""Every constraint kind of the feasibility check, in the order the time scale breaks ties:
the joint kinds (:mod:`dyn_node.core.check.joint_constraints`), then the frame and robot kinds
(:mod:`dyn_node.core.check.task_constraints`) and the base and grasp kinds
(:mod:`dyn_node.core.check.base_constraints`). A module apart so that those modules can subclass
:mod:`~dyn_node.core.check.constraints` without an import cycle."""
from __future__ import annotations

from typing import Mapping

from dyn_node.core.check.base_constraints import BASE_KINDS
from dyn_node.core.check.constraints import Constraint
from dyn_node.core.check.joint_constraints import JOINT_KINDS
from dyn_node.core.check.task_constraints import TASK_KINDS

KINDS: tuple[type[Constraint], ...] = (*JOINT_KINDS, *TASK_KINDS, *BASE_KINDS)
#: The class of each kind name.
KIND_CLASS: Mapping[str, type[Constraint]] = {c.kind: c for c in KINDS}
