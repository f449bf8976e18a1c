"""The limits file travels in the bag: the node records the text its model was built from (and
its sha256) in every ``dyn_node`` metadata record, and dyn-audit rebuilds the limits from it, so
an edited, moved or deleted file on the auditing machine changes nothing but a warning."""
from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import yaml

from test_audit import record_node_run, validated  # noqa: E402

from dyn_node.audit.bag_audit import AuditOptions, model_differences, run_audit
from dyn_node.bag.recorder import Recorder, RecorderConfig
from dyn_node.core.robot.model_source import build_model, limits_text
from dyn_node.core.robot.settings import settings_from_mapping

LIMITS = """\
joint_limits:
  panda_joint1: {has_velocity_limits: true, max_velocity: 2.0}
  panda_joint4: {has_effort_limits: true, max_effort: 60.0}
frame_limits:
  panda_link8:
    point: [0.0, 0.0, 0.1]
    max_linear_speed: 2.5
"""
EDITED = LIMITS.replace("max_velocity: 2.0", "max_velocity: 0.3").replace("speed: 2.5", "speed: 0.05")
OUTPUTS = ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics", "/dyn_node/feasibility",
           "/dyn_node/trajectory_effort")


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _records(path: str) -> list[dict]:
    from mcap.reader import make_reader

    out = []
    for f in sorted(Path(path).glob("*.mcap")):
        with open(f, "rb") as fh:
            out += [dict(r.metadata) for r in make_reader(fh).iter_metadata() if r.name == "dyn_node"]
    return out


def _audit(path: str, out: Path, **kw) -> tuple[dict, int]:
    res = run_audit(AuditOptions(bag=path, out=str(out), report=False, **kw))
    return validated(out), res.exit_code


def _assert_identical(rec: dict) -> None:
    rc = rec["outputs"]["recheck"]
    for topic in OUTPUTS:
        d = rc[topic]
        assert d["matched"] >= 1 and d["identical"] is True, (topic, d)
        assert d["max_abs_difference"] == 0.0 and d.get("comparable", True) is True, (topic, d)


def _record(ros_context, tmp_path: Path, lim: Path) -> str:
    from rclpy.parameter import Parameter

    return record_node_run(ros_context, tmp_path, 200, trajectories_at=(100,),
                           params=[Parameter("limits_file", value=str(lim))])


@pytest.mark.timeout(120)
def test_the_bag_alone_gives_the_limits_after_the_file_is_edited_or_deleted(ros_context, tmp_path):
    lim = tmp_path / "limits.yaml"
    lim.write_text(LIMITS)
    recorded_sha = _sha(lim.read_bytes())
    path = _record(ros_context, tmp_path, lim)
    metas = _records(path)
    assert metas and all(m["limits_yaml"] == LIMITS for m in metas)
    assert all(m["limits_sha256"] == recorded_sha for m in metas)

    # the edit matters: the edited file is another configuration (joint and frame limits)
    settings = settings_from_mapping({"robot_model": "panda", "limits_file": str(lim)})
    original = build_model(settings, limits_yaml=LIMITS)
    lim.write_text(EDITED)
    edited_sha = _sha(lim.read_bytes())
    assert model_differences(original, build_model(settings)) == [
        "limits: velocity", "task limits: frame_limits"]

    rec, code = _audit(path, tmp_path / "edited")
    _assert_identical(rec)
    assert code == 0
    assert rec["configuration"]["model"]["limits_source"] == "bag:limits_yaml"
    assert rec["configuration"]["task_limits"]["frame_limits"]["panda_link8"]["max_linear_speed"] == 2.5
    assert rec["configuration"]["limits"] == original.limits.to_dict()
    warn = [f for f in rec["verdict"]["findings"] if "differs from the text the node read" in f]
    assert warn == [f"the limits file {lim} on this machine (sha256 {edited_sha}) differs from the "
                    f"text the node read (sha256 {recorded_sha}): the bag's recorded text is used"]

    lim.unlink()
    rec, code = _audit(path, tmp_path / "deleted")
    _assert_identical(rec)
    assert code == 0
    assert not [f for f in rec["verdict"]["findings"] if "limits" in f], rec["verdict"]["findings"]

    # --limits keeps overriding: a different file is another configuration, not comparable
    other = tmp_path / "other.yaml"
    other.write_text(EDITED)
    rec, _ = _audit(path, tmp_path / "override", limits=str(other))
    assert rec["configuration"]["model"]["limits_source"] == f"override:{other}"
    fz = rec["outputs"]["recheck"]["/dyn_node/feasibility"]
    assert fz["comparable"] is False and "limits: velocity" in fz["not_comparable"], fz


@pytest.mark.timeout(120)
def test_a_bag_without_the_limits_text_falls_back_to_the_file_and_says_so(ros_context, tmp_path,
                                                                          monkeypatch):
    """An older recorder's bag (no limits_yaml key): the path is read here, as before."""
    import dyn_node.ros.node as node_module

    monkeypatch.setattr(node_module, "limits_text", lambda _model: None)
    lim = tmp_path / "limits.yaml"
    lim.write_text(LIMITS)
    path = _record(ros_context, tmp_path, lim)
    recs = _records(path)
    assert recs and not any("limits_yaml" in m or "limits_sha256" in m for m in recs)
    rec, code = _audit(path, tmp_path / "old")
    _assert_identical(rec)
    assert code == 0
    assert rec["configuration"]["model"]["limits_source"] == (
        f"file:{lim} (not recorded: older recorder)")
    assert (f"the bag does not record the limits file's text (older recorder): {lim} as it is on "
            "this machine is used") in rec["verdict"]["findings"]
    lim.unlink()
    rec, _ = _audit(path, tmp_path / "old_deleted")
    assert rec["configuration"]["model"]["limits_source"].startswith(f"urdf ({lim} not recorded")
    assert any("is not on this machine" in f for f in rec["verdict"]["findings"])


def test_the_model_is_built_from_one_read_of_the_file(tmp_path, monkeypatch):
    """build_model reads the limits file once and remembers that text (what the bag records)."""
    lim = tmp_path / "limits.yaml"
    lim.write_bytes(LIMITS.encode())
    reads: list[Path] = []
    for name in ("read_bytes", "read_text"):
        orig = getattr(Path, name)

        def spy(self, *a, _orig=orig, **kw):
            if self == lim:
                reads.append(self)
            return _orig(self, *a, **kw)
        monkeypatch.setattr(Path, name, spy)
    import dyn_node.core.robot.limits_file as limits_file
    orig_read = limits_file.read_bytes

    def spy_read(path, *a, **kw):
        if Path(path) == lim:
            reads.append(Path(path))
        return orig_read(path, *a, **kw)
    monkeypatch.setattr(limits_file, "read_bytes", spy_read)   # the bounded regular-file read
    model = build_model(settings_from_mapping({"robot_model": "panda", "limits_file": str(lim)}))
    assert len(reads) == 1
    assert limits_text(model) == LIMITS
    assert [(f.frame, f.max_linear_speed) for f in model.task_limits.frame_limits] == [("panda_link8", 2.5)]
    assert model.task_limits.source == str(lim)  # errors and warnings still name the file
    assert limits_text(build_model(settings_from_mapping({"robot_model": "panda"}))) is None


def test_each_configuration_record_carries_its_limits_text(tmp_path):
    """Recorder: the limits text and its sha256 in the first record and in each later one."""
    rec = Recorder(RecorderConfig(directory=str(tmp_path), fsync=False), parameters_yaml="a: 1\n",
                   effective_log_time_ns=5, limits_yaml=LIMITS)
    rec.set_parameters_yaml("a: 2\n", effective_log_time_ns=7, limits_yaml=EDITED)
    rec.set_parameters_yaml("a: 3\n", effective_log_time_ns=9)
    rec.close()
    metas = _records(str(rec.path))
    assert [(m["parameters"], m.get("limits_yaml"), m.get("limits_sha256")) for m in metas] == [
        ("a: 1\n", LIMITS, _sha(LIMITS.encode())), ("a: 2\n", EDITED, _sha(EDITED.encode())),
        ("a: 3\n", None, None)]
    assert yaml.safe_load(metas[0]["limits_yaml"])["frame_limits"]["panda_link8"]["max_linear_speed"] == 2.5


@pytest.mark.timeout(120)
def test_switching_the_limits_file_mid_recording_records_the_new_text(ros_context, tmp_path):
    """limits_file set to another file while recording: the record written with the change holds
    that file's text, and the audit replays each part with its own limits, both files edited."""
    from rclpy.parameter import Parameter

    first, second = tmp_path / "first.yaml", tmp_path / "second.yaml"
    first.write_text(LIMITS)
    second.write_text(LIMITS.replace("max_velocity: 2.0", "max_velocity: 1.9"))
    texts = {first: first.read_text(), second: second.read_text()}
    path = record_node_run(ros_context, tmp_path, 200, trajectories_at=(50, 150), params=[
        Parameter("limits_file", value=str(first))], at={
        100: lambda node: node.set_parameters([Parameter("limits_file", value=str(second))])})
    metas = _records(path)
    assert metas[0]["limits_yaml"] == texts[first] and metas[-1]["limits_yaml"] == texts[second]
    assert metas[-1]["limits_sha256"] == _sha(second.read_bytes())
    assert int(metas[-1]["effective_log_time_ns"]) > int(metas[0]["effective_log_time_ns"])
    for f in (first, second):
        f.write_text(EDITED)
    rec, code = _audit(path, tmp_path / "out")
    _assert_identical(rec)
    assert [c["parameters"] for c in rec["configuration"]["changes"]] == [{"limits_file": str(second)}]
    assert rec["outputs"]["recheck"]["/dyn_node/feasibility"]["matched"] == 2
    assert sum("differs from the text the node read" in f for f in rec["verdict"]["findings"]) == 2
    assert code == 0
