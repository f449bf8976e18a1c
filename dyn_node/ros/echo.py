"""``python -m dyn_node.ros.echo TOPIC [-n N] [--timeout S]``: print a topic's messages as YAML
documents (``---`` between them), like ``ros2 topic echo``, for a set-up with only the venv (no
``ros2`` command). The type is taken from the graph; a latched topic (every publisher transient
local, e.g. ``/dyn_node/feasibility``) is read latched, a best-effort one best effort.
Exit 0 after N messages (or Ctrl-C, or SIGTERM: quietly), 1 when no publisher appeared within ``--timeout``."""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import time
from typing import Any, Sequence

import yaml


def to_plain(value: Any) -> Any:
    """A message (or field) as plain Python for YAML: messages as mappings in field order,
    arrays as lists, ``byte`` fields (one-byte ``bytes`` in rclpy) as integers."""
    if hasattr(value, "get_fields_and_field_types"):
        return {f: to_plain(getattr(value, f)) for f in value.get_fields_and_field_types()}
    if isinstance(value, (bytes, bytearray)):
        return value[0] if len(value) == 1 else list(value)
    if hasattr(value, "tolist"):  # numpy arrays and scalars, array.array
        return to_plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    return value


def _message_class(type_name: str) -> Any:
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def _qos(publishers: Sequence[Any]) -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


def _find(node: Any, topic: str, timeout_s: float) -> tuple[str, list] | None:
    """(type name, publishers' endpoint infos) once ``topic`` has a publisher, or None."""
    import rclpy
    deadline = None if timeout_s <= 0 else time.monotonic() + timeout_s
    while deadline is None or time.monotonic() < deadline:
        types = dict(node.get_topic_names_and_types())
        pubs = node.get_publishers_info_by_topic(topic)
        if types.get(topic) and pubs:
            return types[topic][0], pubs
        rclpy.spin_once(node, timeout_sec=0.1)
    return None


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m dyn_node.ros.echo", description=__doc__.split("\n")[0])
    ap.add_argument("topic", help="topic name, e.g. /dyn_node/gravity_torque")
    ap.add_argument("-n", "--count", type=int, default=0, help="exit after N messages (0: run on)")
    ap.add_argument("--timeout", type=float, default=0.0,
                    help="give up after this many seconds without a publisher (0: wait)")
    args = ap.parse_args(argv)
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    # SIGTERM (``timeout``) stops it as Ctrl-C does, wherever it lands (rclpy's own handler
    # shut the context down under whatever call was running: a traceback)
    signal.signal(signal.SIGTERM, _interrupt)
    node = None
    try:
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("dyn_node_echo")
        return _echo(node, args)
    except KeyboardInterrupt:
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def _interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def _echo(node: Any, args: argparse.Namespace) -> int:
    import rclpy

    topic = node.resolve_topic_name(args.topic)
    found = _find(node, topic, args.timeout)
    if found is None:
        print(f"echo: no publisher on {topic} within {args.timeout:g} s", file=sys.stderr)
        return 1
    type_name, pubs = found
    seen = [0]

    def on_message(msg: Any) -> None:
        sys.stdout.write(yaml.safe_dump(to_plain(msg), sort_keys=False) + "---\n")
        sys.stdout.flush()
        seen[0] += 1

    node.create_subscription(_message_class(type_name), topic, on_message, _qos(pubs))
    while rclpy.ok() and not (args.count and seen[0] >= args.count):
        rclpy.spin_once(node, timeout_sec=0.5)
    return 0

if __name__ == "__main__":
    sys.exit(main())
