"""Two notes of the demo's output: where a run writes (a new bag per run, earlier ones kept),
and why the audit found inputs the live node did not answer (its own count, read from the bag:
joint_states taken before it had its model, which comes from /robot_description). Pure: no
rclpy."""
from __future__ import annotations

from pathlib import Path

from dyn_node.bag.reader import BagReader, MessageDecoder
from dyn_node.errors import DynNodeError

JOINT_STATES_STATUS = "dyn_node: joint_states"


def where_line(out: Path) -> str:
    """What a run writes under ``out`` (the demo's ``--out``), and how many bags are there."""
    bags = out / "bags"
    old = sum(1 for p in bags.iterdir() if p.is_dir()) if bags.is_dir() else 0
    return (f"writing to {out}: a new bag in {bags}/dyn_node_<UTC time>/ (each run adds one; "
            f"{old} from earlier runs kept), audit/, logs/, samples.npz and summary.json "
            "(replaced)")


def before_model_in_bag(bag: Path, topic: str = "/diagnostics") -> int | None:
    """``before_model_messages`` of the last ``dyn_node: joint_states`` status recorded in
    ``bag`` (joint_states the node took before it had a model), or None if there is none."""
    decoder = MessageDecoder()
    found: int | None = None
    try:
        for m in BagReader(bag, topics=[topic]).messages():
            for status in decoder.decode(m.channel, m.data).status:
                if status.name == JOINT_STATES_STATUS:
                    found = next((int(kv.value) for kv in status.values
                                  if kv.key == "before_model_messages"), found)
    except (DynNodeError, OSError, ValueError):  # an unreadable bag: the reason stays unknown
        return None
    return found


def unanswered_reason(unanswered: int, before_model: int | None) -> str:
    """Beside "not answered live N": the node's own count of inputs taken before its model."""
    if not unanswered:
        return ""
    if before_model is None:
        return " (the bag has no joint_states status to say why)"
    if before_model == unanswered:
        return " (all taken before dyn_node had its model from /robot_description)"
    return (f" (dyn_node counted {before_model} joint_states taken before it had its model "
            "from /robot_description)")


__all__ = ["before_model_in_bag", "unanswered_reason", "where_line"]
