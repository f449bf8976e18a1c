"""The question services' recorded calls counted from a bag without dyn_node's reader or audit:
read with the official ``mcap`` reader, decoded by ``rosbags`` from the schema embedded in the bag.
A call is one server-side response event (``RESPONSE_SENT``, 2); it is answered "no" when not
accepted (whatever the reason: invalid, busy, no_model) or, for a check or retime, not feasible."""
from __future__ import annotations

from pathlib import Path

KIND_OF_TYPE = {"dyn_node_interfaces/srv/CheckTrajectory_Event": "check",
                "dyn_node_interfaces/srv/ComputeInverseDynamics_Event": "inverse_dynamics",
                "dyn_node_interfaces/srv/RetimeTrajectory_Event": "retime"}
RESPONSE_SENT = 2


def responses(bag: Path) -> list[tuple[str, object]]:
    """(kind, response) of every server-side response event in the bag, in file order."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    files = sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag]
    out = []
    for f in files:
        with open(f, "rb") as fh:
            for schema, _channel, msg in make_reader(fh).iter_messages():
                if schema is None or schema.name not in KIND_OF_TYPE:
                    continue
                ts = get_typestore(Stores.EMPTY)
                types = get_types_from_msg(schema.data.decode(), schema.name)
                ts.register(types)
                ev = ts.deserialize_cdr(msg.data, next(k for k in types if k.endswith("_Event")))
                if ev.info.event_type == RESPONSE_SENT and len(ev.response):
                    out.append((KIND_OF_TYPE[schema.name], ev.response[0]))
    return out


def question_counts(bag: Path) -> dict[str, tuple[int, int]]:
    """kind → (calls answered, answered "no")."""
    counts: dict[str, tuple[int, int]] = {}
    for kind, r in responses(bag):
        no = (not r.accepted) or (kind != "inverse_dynamics" and not r.feasible)
        n, bad = counts.get(kind, (0, 0))
        counts[kind] = (n + 1, bad + int(no))
    return counts


def gate_records(bag: Path) -> list[dict]:
    """The gate's ``~/gate_decisions`` records (std_msgs/String holding JSON) in the bag's log
    time order, read by the official mcap reader and decoded by rosbags."""
    import json

    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    files = sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag]
    out = []
    for f in files:
        with open(f, "rb") as fh:
            for schema, channel, msg in make_reader(fh).iter_messages(log_time_order=True):
                if not channel.topic.endswith("/gate_decisions"):
                    continue
                ts = get_typestore(Stores.EMPTY)
                ts.register(get_types_from_msg(schema.data.decode(), schema.name))
                out.append(json.loads(ts.deserialize_cdr(msg.data, schema.name).data))
    return out


def gate_goal_counts(bag: Path) -> tuple[int, int]:
    """(goals decided, goals executed "no") from the gate's records: a goal was sent to be
    executed; it is "no" when rejected or not forwarded (the controller absent, late or refusing),
    forwarded with an infeasible verdict (check mode), or ended without the controller's result
    (silent, cancel unconfirmed); a retimed goal forwarded a feasible one."""
    n = bad = 0
    given_up = {r["goal_id"] for r in gate_records(bag)
                if r.get("event") in ("downstream_silent", "downstream_cancel_unconfirmed")}
    for rec in gate_records(bag):
        if rec.get("event") != "decision":
            continue
        n += 1
        ok = rec["decision"] == "retimed" or (rec["decision"] == "forwarded" and rec["feasible"])
        bad += not ok or rec["goal_id"] in given_up
    return n, bad
