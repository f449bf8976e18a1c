"""Retiming: the fastest trajectory along the same path that passes the exact feasibility check
(docs/retime.md)."""
from dyn_node.retime.result import RetimeResult
from dyn_node.retime.retimer import retime

__all__ = ["retime", "RetimeResult"]
