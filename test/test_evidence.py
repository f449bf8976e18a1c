"""EvidenceRecord builder and its shipped JSON Schema (draft 2020-12)."""
from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import pytest

from dyn_node import __version__
from dyn_node.errors import CONTROL_ERROR, PLANNING_ERROR
from dyn_node.audit.evidence import (SCHEMA_PATH, EvidenceError, EvidenceRecord, jsonable, schema,
                               validate)


def minimal_record() -> EvidenceRecord:
    rec = EvidenceRecord(kind="audit", tool="dyn-audit")
    rec.verdict = {"result": "feasible", "exit_code": 0, "summary": "ok", "partial": False}
    rec.inputs = {"bag": "/b", "files": [], "topics": [], "message_counts": {},
                  "time_span": {"start_ns": None, "end_ns": None, "duration_s": 0.0}}
    rec.configuration = {"model": {"name": "r", "urdf_sha256": "x", "joint_names": ["a"], "source": "s"},
                         "limits": {}, "parameters": {}, "overrides": {}}
    rec.outputs = {"trajectories": [], "effort": {"per_joint": []}, "violations": [],
                   "controller_states": {}, "recheck": {}, "latency": {}}
    rec.input_quality = {"gaps": [], "stale_periods": [],
                         "invalid_messages": {"count": 0, "by_reason": {}, "examples": []},
                         "out_of_order": {"count": 0, "examples": []}, "unreadable_ranges": []}
    return rec


def test_schema_is_a_valid_draft_2020_12_schema_shipped_in_the_package():
    assert SCHEMA_PATH.parts[-2:] == ("schemas", "evidence_record.schema.json")
    s = json.loads(SCHEMA_PATH.read_text())
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(s)


def test_jsonable_maps_non_finite_numbers_and_numpy():
    out = jsonable({"a": np.float64(1.5), "b": np.inf, "c": -math.inf, "d": math.nan,
                    "e": np.arange(3), "f": (np.int64(2), np.bool_(True)), 3: None})
    assert out == {"a": 1.5, "b": "inf", "c": "-inf", "d": None, "e": [0, 1, 2], "f": [2, True],
                   "3": None}
    json.dumps(out, allow_nan=False)


def test_record_round_trip_and_required_sections(tmp_path):
    rec = minimal_record()
    rec.add_label(CONTROL_ERROR)
    rec.add_label(CONTROL_ERROR)
    rec.add_label(PLANNING_ERROR)
    d = rec.write(tmp_path / "e.json")
    back = json.loads((tmp_path / "e.json").read_text())
    assert back == d
    assert back["failure_labels"] == [CONTROL_ERROR, PLANNING_ERROR]
    assert back["tool"] == {"name": "dyn-audit", "version": __version__}
    assert back["seed"]["used"] is False and back["seed"]["value"] is None
    assert "utilisation" in back["metric_definitions"] and back["metric_definitions"]["time_scale"]["unit"] == "1"
    jsonschema.Draft202012Validator(schema()).validate(back)
    with pytest.raises(EvidenceError):
        rec.add_label("made-up label")


def test_schema_rejects_what_it_must():
    good = minimal_record().to_dict()
    for mutate in (
        lambda r: r.pop("input_quality"),
        lambda r: r["input_quality"]["unreadable_ranges"].append({"start_s": 0.0, "end_s": 1.0}),
        lambda r: r["verdict"].update(exit_code=4),  # 0-3 are the audit's codes
        lambda r: r["inputs"]["time_span"].update(duration_s="-inf"),  # never negative
        lambda r: r["inputs"]["time_span"].update(duration_s="infinite"),
        lambda r: r["failure_labels"].append("oops"),
        lambda r: r["outputs"]["violations"].append({"joint": "a", "kind": "effort"}),
        lambda r: r.update(extra=1),
        lambda r: r["outputs"]["trajectories"].append({"index": 0, "topic": "t", "time_s": 0.0,
                                                        "stamp_ns": 0, "accepted": True,
                                                        "feasible": True, "failure_label": None,
                                                        "time_scale": "fast"}),
    ):
        bad = json.loads(json.dumps(good))
        mutate(bad)
        with pytest.raises(EvidenceError):
            validate(bad)
    ok = json.loads(json.dumps(good))
    ok["input_quality"]["unreadable_ranges"].append({"start_s": 1.0, "end_s": None, "reason": "cut"})
    validate(ok)
