"""dyn-fleet: a fleet of generated bags audited as Ray tasks, on local Ray and a two-node cluster.

Expected values come from how the bags were generated (robot, length, where the effort spike
is and how high), not from the audit's own numbers; the identity with dyn-audit is checked by
running dyn-audit on each bag alone. Every Ray process is bound to 127.0.0.1 (checked on the
listening sockets of every process this test started).
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import time
from pathlib import Path

# before Ray is imported anywhere in this process: loopback only, no usage statistics
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

import pytest  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet_bags import BagSpec, damage_chunk, truncate, write_bag  # noqa: E402

from dyn_node.fleet import engine as fleet  # noqa: E402
from dyn_node.audit.bag_audit import main as audit_main  # noqa: E402
from dyn_node.core.robot.model import load_model  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RATE = 500.0
# name → spec; the kind of damage applied after writing is in DAMAGE
SPECS = [
    BagSpec("panda_ok_a", "panda", 1.0, questions=(True, False), start_s=0),
    BagSpec("panda_ok_b", "panda", 2.0, trajectories=(False,), start_s=100),
    BagSpec("panda_ok_c", "panda", 0.4, start_s=200),
    BagSpec("panda_spike_a", "panda", 1.0, spike=(0.5, 0.6), questions=(True,), start_s=300),
    BagSpec("panda_spike_b", "panda", 2.0, spike=(1.0, 1.3), start_s=400),
    BagSpec("panda_fast", "panda", 1.0, trajectories=(False, True), start_s=500),
    BagSpec("panda_spike_fast", "panda", 1.5, spike=(0.2, 0.25), trajectories=(True,), start_s=600),
    BagSpec("ur5_ok_a", "ur5", 1.0, start_s=700),
    BagSpec("ur5_ok_b", "ur5", 3.0, trajectories=(False,), questions=(True,), start_s=800),
    BagSpec("ur5_spike", "ur5", 1.0, spike=(0.1, 0.2), start_s=900),
    BagSpec("ur5_fast", "ur5", 1.0, trajectories=(True, True), start_s=1000),
    BagSpec("ur5_ok_c", "ur5", 0.6, start_s=1100),
    BagSpec("planar_ok_a", "planar_2link", 1.0, start_s=1200),
    BagSpec("planar_ok_b", "planar_2link", 2.5, trajectories=(False,), start_s=1300),
    BagSpec("planar_fast", "planar_2link", 1.0, trajectories=(True,), start_s=1400),
    BagSpec("planar_ok_c", "planar_2link", 0.3, start_s=1500),
    BagSpec("panda_damaged", "panda", 2.0, start_s=1600),
    BagSpec("ur5_truncated", "ur5", 2.0, start_s=1700),
    BagSpec("panda_nomodel", "panda", 0.5, model=False, start_s=1800),
    BagSpec("panda_empty", "panda", 0.0, start_s=1900),
]
DAMAGE = {"panda_damaged": "chunk", "ur5_truncated": "truncate"}
LOOSE = "loose_panda"      # a single .mcap file copied out of a bag (a loose file in a root)
JUNK = "junk"              # a .mcap file that is not MCAP
VOLATILE_ROW = ("audit_s", "audited_utc", "node", "resumed")
VOLATILE_EVIDENCE = ("started_utc", "finished_utc", "duration_s")


def build_fleet(root: Path, specs=SPECS) -> dict[str, Path]:
    """Write the bags in a nested layout (three sub-directories) and damage the damaged ones."""
    paths: dict[str, Path] = {}
    for k, spec in enumerate(specs):
        sub = root / ("site_a", "site_b/day1", "site_b/day2")[k % 3]
        sub.mkdir(parents=True, exist_ok=True)
        bag = write_bag(sub, spec)
        if DAMAGE.get(spec.name) == "chunk":
            damage_chunk(bag, 1)
        elif DAMAGE.get(spec.name) == "truncate":
            truncate(bag, 0.6)
        paths[spec.name] = bag
    loose = root / f"{LOOSE}.mcap"
    shutil.copy(next(paths["panda_ok_a"].glob("*.mcap")), loose)
    paths[LOOSE] = loose
    junk = root / "site_a" / f"{JUNK}.mcap"
    junk.write_bytes(b"\x00" * 100)
    paths[JUNK] = junk
    return paths


def spec_of(name: str) -> BagSpec | None:
    if name == LOOSE:
        return SPECS[0]
    return next((s for s in SPECS if s.name == name), None)


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    paths = build_fleet(root / "bags")
    out = root / "out"
    import io
    from contextlib import redirect_stderr, redirect_stdout

    so, se = io.StringIO(), io.StringIO()
    with redirect_stdout(so), redirect_stderr(se):
        code = fleet.main([str(root / "bags"), "--out", str(out), "--workers", "2"])
    rows = pq_rows(out / "fleet.parquet")
    by_name = {Path(r["path"]).name.removesuffix(".mcap"): r for r in rows}
    return {"root": root, "paths": paths, "out": out, "code": code, "stdout": so.getvalue(),
            "stderr": se.getvalue(), "rows": rows, "by_name": by_name}


def pq_rows(path: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()


def _spike_ratio(spec: BagSpec) -> tuple[float, float, int]:
    """(peak ratio, peak time, samples) of the spike as write_bag makes it: joint 2's effort
    1.05·limit + (t − start) on the samples with start ≤ t < end."""
    limit = float(load_model(builtin=spec.robot).limits.effort[1])
    ts = [i / spec.rate_hz for i in range(int(round(spec.seconds * spec.rate_hz)))
          if spec.spike[0] <= i / spec.rate_hz < spec.spike[1]]
    return (limit * 1.05 + (ts[-1] - spec.spike[0])) / limit, ts[-1], len(ts)


# --- every row right --------------------------------------------------------------------------
def test_every_row_is_right_and_damaged_bags_are_isolated(fleet_run):
    rows, by = fleet_run["rows"], fleet_run["by_name"]
    assert len(rows) == len(SPECS) + 2 == len({r["bag_id"] for r in rows})
    assert set(by) == {s.name for s in SPECS} | {LOOSE, JUNK}
    for name, r in by.items():
        assert name in r["bag_id"] and r["path"] == str(fleet_run["paths"][name])
        spec = spec_of(name)
        if name == JUNK:
            assert (r["exit_category"], r["error_code"], r["exit_code"]) == ("unusable", "bag_unreadable", 2)
            assert "not an MCAP file" in r["error"] and r["evidence"] == ""
            continue
        if name == "panda_nomodel":
            assert (r["exit_category"], r["error_code"], r["verdict"]) == ("unusable", "no_model", "error")
            assert "--robot-model" in r["error"] and r["content_hash"]
            continue
        if name == "panda_empty":
            assert (r["exit_category"], r["error_code"]) == ("unusable", "no_inputs")
            continue
        n = int(round(spec.seconds * RATE))
        assert r["robot"] == spec.robot and r["dof"] == load_model(builtin=spec.robot).nv
        assert r["recording_start_ns"] == 1_700_000_000_000_000_000 + int(spec.start_s * 1e9)
        assert r["error"] == "" and r["evidence"] == f"bags/{r['bag_id']}/evidence.json"
        assert (fleet_run["out"] / r["evidence"]).is_file() and (fleet_run["out"] / r["report"]).is_file()
        if name in DAMAGE:
            assert r["partial"] is True and r["exit_code"] == 3 and r["exit_category"] == "partial"
            assert r["unreadable_ranges"] >= 1 and 0 < r["joint_states"] < n
            if DAMAGE[name] == "chunk":
                assert r["chunks_damaged"] == 1
            continue
        assert r["partial"] is False and r["unreadable_ranges"] == 0 and r["chunks_damaged"] == 0
        assert r["joint_states"] == r["joint_states_accepted"] == n
        # executed trajectories and check-only questions apart: a question's "no" is no violation
        assert r["trajectories"] == len(spec.trajectories)
        assert r["trajectories_bad"] == sum(spec.trajectories)
        assert (r["questions"], r["questions_infeasible"]) == (len(spec.questions), sum(spec.questions))
        assert r["messages"] == n + len(spec.trajectories) + len(spec.questions) + 1  # + the description
        assert r["recording_duration_s"] == pytest.approx((n - 1) / RATE, abs=1e-9)
        assert r["invalid_messages"] == r["out_of_order_messages"] == r["gaps"] == 0
        violating = bool(spec.spike) or any(spec.trajectories)
        assert r["exit_code"] == (1 if violating else 0)
        assert r["verdict"] == ("violations" if violating else "feasible")
        if spec.spike:
            ratio, t_peak, k = _spike_ratio(spec)
            assert r["live_effort_episodes"] == r["live_episodes_total"] == 1
            if not any(spec.trajectories):
                assert (r["worst_joint"], r["worst_constraint"], r["worst_source"]) == (
                    load_model(builtin=spec.robot).joint_names[1], "effort", "live")
                assert r["worst_ratio"] == pytest.approx(ratio, rel=1e-12)
                assert r["worst_time_s"] == pytest.approx(t_peak, abs=1e-9)
        else:
            assert r["live_episodes_total"] == 0
        if any(spec.trajectories):
            assert r["worst_time_scale"] > 1.0 and r["worst_source"] == "trajectory"
            assert sum(r[f"traj_{k}_violations"] for k in fleet.TRAJ_KINDS) > 0
        elif spec.trajectories:
            assert r["worst_time_scale"] <= 1.0
            assert sum(r[f"traj_{k}_violations"] for k in fleet.TRAJ_KINDS) == 0
        else:
            assert math.isnan(r["worst_time_scale"])
        if not violating:
            assert r["worst_ratio"] < 1.0 and r["exit_category"] == "ok"
    # violations win over the partial and unusable bags
    assert fleet_run["code"] == 1
    # and the damaged bags are said, whatever won the exit code
    first, second = fleet_run["stdout"].splitlines()[:2]
    assert first.startswith("VIOLATIONS: 22 bags: ") and first.endswith(" (2 partial: data lost)"), first
    # executed and questions over the bags audited whole (the damaged ones lost some of theirs)
    whole = [spec_of(n) for n, r in by.items() if r["verdict"] != "error" and n not in DAMAGE]
    lost = [by[n] for n in DAMAGE]
    assert second == (
        f"trajectories: {sum(sum(s.trajectories) for s in whole) + sum(r['trajectories_bad'] for r in lost)} of "
        f"{sum(len(s.trajectories) for s in whole) + sum(r['trajectories'] for r in lost)} executed infeasible "
        f"or rejected; questions: {sum(sum(s.questions) for s in whole)} of "
        f"{sum(len(s.questions) for s in whole)} answered infeasible or rejected (not violations)")


def test_joint_rows_match_the_bags(fleet_run):
    import pyarrow.parquet as pq

    joints = pq.read_table(fleet_run["out"] / "fleet_joints.parquet").to_pylist()
    by_id = {r["bag_id"]: r for r in fleet_run["rows"]}
    audited = [r for r in fleet_run["rows"] if r["verdict"] != "error"]
    assert len(joints) == sum(r["dof"] for r in audited)
    for name, r in fleet_run["by_name"].items():
        spec = spec_of(name)
        if r["verdict"] == "error":
            assert not [j for j in joints if j["bag_id"] == r["bag_id"]]
            continue
        mine = sorted((j for j in joints if j["bag_id"] == r["bag_id"]), key=lambda j: j["joint_index"])
        assert [j["joint"] for j in mine] == list(load_model(builtin=spec.robot).joint_names)
        assert all(j["robot"] == spec.robot and by_id[j["bag_id"]] for j in mine)
        if spec.spike and name not in DAMAGE:
            ratio, _t, k = _spike_ratio(spec)
            assert mine[1]["live_effort_peak"] == pytest.approx(ratio, rel=1e-12)
            assert mine[1]["live_effort_over_s"] == pytest.approx((k - 1) / RATE, abs=1e-9)
            assert mine[1]["live_episodes"] == 1 and mine[0]["live_episodes"] == 0
        if not spec.trajectories:
            assert all(math.isnan(j["traj_effort_peak"]) for j in mine)


def test_progress_bar_on_stderr(fleet_run):
    err = fleet_run["stderr"]
    last = err.strip().splitlines()[-1]
    assert re.search(r"22/22 bags +ETA 0:00 +\d+ with violations +3 failed", last), last
    assert "Traceback" not in err


# --- the tables, as pyarrow and DuckDB read them ------------------------------------------------
ARROW = {"string": "string", "int8": "int8", "int32": "int32", "int64": "int64",
         "float64": "double", "bool": "bool"}
DUCK = {"string": "VARCHAR", "int8": "TINYINT", "int32": "INTEGER", "int64": "BIGINT",
        "float64": "DOUBLE", "bool": "BOOLEAN"}


@pytest.mark.parametrize("table, columns", [("fleet.parquet", fleet.ROW_COLUMNS),
                                            ("fleet_joints.parquet", fleet.JOINT_COLUMNS)])
def test_parquet_schema_read_by_pyarrow_and_duckdb(fleet_run, table, columns):
    import duckdb
    import pyarrow.parquet as pq

    path = fleet_run["out"] / table
    schema = pq.read_schema(path)
    assert [(f.name, str(f.type)) for f in schema] == [(n, ARROW[t]) for n, t, *_ in columns]
    assert {f.name: f.metadata[b"unit"].decode() for f in schema} == {n: u for n, _t, u, _d in columns}
    con = duckdb.connect()
    described = con.execute(f"DESCRIBE SELECT * FROM read_parquet('{path}')").fetchall()
    assert [(d[0], d[1]) for d in described] == [(n, DUCK[t]) for n, t, *_ in columns]
    n = con.execute(f"SELECT count(*) FROM '{path}'").fetchone()[0]
    assert n == pq.read_metadata(path).num_rows > 0


def test_duckdb_answers_match_the_rows(fleet_run):
    import duckdb

    path = fleet_run["out"] / "fleet.parquet"
    got = dict(duckdb.sql(f"SELECT exit_category, count(*) FROM '{path}' GROUP BY 1").fetchall())
    want: dict[str, int] = {}
    for r in fleet_run["rows"]:
        want[r["exit_category"]] = want.get(r["exit_category"], 0) + 1
    assert got == want == {"ok": 10, "violations": 7, "partial": 2, "unusable": 3}
    worst = duckdb.sql(f"SELECT path FROM '{path}' WHERE verdict = 'violations' AND worst_source = "
                       "'live' ORDER BY worst_ratio DESC LIMIT 1").fetchall()[0][0]
    ratios = {s.name: _spike_ratio(s)[0] for s in SPECS if s.spike and not any(s.trajectories)}
    assert Path(worst).name == max(ratios, key=ratios.get)


def _fleet_page() -> str:
    """dyn-fleet's reference page (docs/fleet.md, linked from the README's contents)."""
    text = (REPO / "docs" / "fleet.md").read_text()
    assert text.startswith("# Fleet audit: `dyn-fleet`\n")
    return text


def test_docs_document_every_column():
    section = _fleet_page()
    for name, typ, unit, _d in fleet.ROW_COLUMNS + fleet.JOINT_COLUMNS:
        m = re.search(rf"^\| `{re.escape(name)}` \| (\w+) \| ([^|]*(?:\\\|[^|]*)*) \|", section, re.M)
        assert m and m.group(1) == typ and m.group(2).strip() == (unit or "–"), name
    assert "127.0.0.1" in section and "RAY_USAGE_STATS_ENABLED=0" in section
    assert "every\n  node" in section or "every node" in section.replace("\n", " ").replace("**", "")


def test_docs_duckdb_one_liners_run(fleet_run):
    import subprocess

    import duckdb

    lines = [ln for ln in _fleet_page().splitlines() if ln.startswith("python -c") and "duckdb" in ln]
    assert len(lines) == 2
    for line in lines:
        res = subprocess.run(line, shell=True, cwd=fleet_run["root"], capture_output=True, text=True,
                             timeout=60, env=dict(os.environ, PATH=f"{Path(sys.executable).parent}:{os.environ['PATH']}"))
        assert res.returncode == 0, res.stderr
    sql = [ln.split('duckdb.sql(\\"', 1)[1].split('\\")', 1)[0] for ln in lines]
    con = duckdb.connect()
    con.execute(f"SET file_search_path = '{fleet_run['root']}'")
    summary = con.execute(sql[0]).fetchall()
    worst = [w for *_x, w in summary]
    # usable bags first, by their worst ratio; the groups with no ratio (NaN) last, as NULL
    finite = [w for w in worst if w is not None]
    assert finite and all(not math.isnan(w) for w in finite) and finite == sorted(finite, reverse=True)
    assert worst == finite + [None] * (len(worst) - len(finite)) and len(finite) < len(worst)
    partial = {name: r["partial"] for name, r in fleet_run["by_name"].items()}
    by_cat = {(r[0], r[1]): r[3] for r in summary}
    assert sum(by_cat.values()) == sum(partial.values()) == 2
    assert {Path(p).name for p, *_ in con.execute(sql[1]).fetchall()} == {n for n, v in partial.items() if v}


def test_fleet_html_is_self_contained(fleet_run):
    page = (fleet_run["out"] / "fleet.html").read_text()
    assert page.count("data:image/png;base64,") == 2
    srcs = re.findall(r'src="([^"]+)"', page)
    assert srcs and all(s.startswith("data:") for s in srcs)
    hrefs = re.findall(r'href="([^"]+)"', page)
    assert hrefs and all(h.startswith("bags/") and (fleet_run["out"] / h).is_file() for h in hrefs)
    assert "dyn-fleet: VIOLATIONS" in page and "panda_nomodel" in page


# --- identical to dyn-audit on a bag alone --------------------------------------------------------
def _strip(rec: dict) -> dict:
    rec = json.loads(json.dumps(rec))
    for k in VOLATILE_EVIDENCE:
        rec["timestamps"].pop(k)
    return rec


def test_each_bag_gives_what_dyn_audit_gives_alone(fleet_run, tmp_path, capsys):
    for name, r in fleet_run["by_name"].items():
        alone = tmp_path / r["bag_id"]
        code = audit_main([r["path"], "--out", str(alone)])
        capsys.readouterr()
        assert code == r["exit_code"], name
        if r["verdict"] == "error":
            assert not (alone / "evidence.json").exists()
            continue
        mine = json.loads((fleet_run["out"] / r["evidence"]).read_text())
        theirs = json.loads((alone / "evidence.json").read_text())
        assert _strip(mine) == _strip(theirs), name
        # and the row is what dyn-audit's own record says, read here without the fleet's code
        want = _expected_row(theirs)
        assert _differing({k: r[k] for k in want}, want) == [], name


def _num(x) -> float:
    return float(x) if isinstance(x, (int, float)) else (float(x) if x in ("inf", "-inf") else math.nan)


def _expected_row(rec: dict) -> dict:
    """The row's record-derived columns, parsed from evidence.json here (not by row_from_record):
    the worst of the live peaks, the live episodes and the *executed* trajectories only."""
    out, iq, inp = rec["outputs"], rec["input_quality"], rec["inputs"]
    trajs = out["trajectories"]
    executed = [t for t in trajs if t["request"] == "execute"]
    services = list(out.get("questions", {}).values())
    cands = [(_num(p["peak_utilisation"]), p["joint"], "effort", "live", _num(p["peak_time_s"]))
             for p in out["effort"]["per_joint"]]
    cands += [(_num(v["peak_ratio"]), v["joint"], v["kind"], "live", _num(v["peak_time_s"]))
              for v in out["violations"]]
    cands += [(_num(t["worst_ratio"]), t["worst_joint"], t["worst_constraint"], "trajectory",
               _num(t["time_s"])) for t in executed if t["accepted"]]
    cands = [c for c in cands if not math.isnan(c[0])]
    best = max(cands, key=lambda c: c[0]) if cands else (math.nan, "", "", "", math.nan)
    scales = [x for x in (_num(t["time_scale"]) for t in executed if t["accepted"]) if not math.isnan(x)]
    row = {"robot": rec["configuration"]["model"]["name"], "dof": len(rec["configuration"]["model"]["joint_names"]),
           "recording_start_ns": inp["time_span"]["start_ns"],
           "messages": sum(inp["message_counts"].values()),
           "joint_states": out["monitor_counts"]["received"],
           "joint_states_accepted": out["monitor_counts"]["accepted"],
           "trajectories": len(executed), "trajectories_bad": sum(not t["feasible"] for t in executed),
           # request-topic questions are listed; service questions counted per service
           "questions": len(trajs) - len(executed) + sum(q["answered"] for q in services),
           "questions_infeasible": sum(not t["feasible"] for t in trajs if t["request"] != "execute")
           + sum(q["infeasible"] + sum(q["not_accepted"].values()) for q in services),
           "verdict": rec["verdict"]["result"], "partial": rec["verdict"]["partial"],
           "worst_ratio": best[0], "worst_joint": best[1], "worst_constraint": best[2],
           "worst_source": best[3], "worst_time_s": best[4],
           "worst_time_scale": max(scales) if scales else math.nan,
           "live_episodes_total": out["violation_episodes_total"],
           "invalid_messages": iq["invalid_messages"]["count"], "unreadable_ranges": len(iq["unreadable_ranges"]),
           "gaps": iq["gaps_total"], "chunks_damaged": iq["chunks_damaged"]}
    for k in fleet.TRAJ_KINDS:
        row[f"traj_{k}_violations"] = sum(_num((kinds.get(k) or {}).get("ratio")) > 1.0 for t in executed
                                          for kinds in (t.get("per_joint") or {}).values())
    return row


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _differing(a: dict, b: dict, *, skip=()) -> list[str]:
    """Keys whose values differ (NaN equals NaN; int and float never equal)."""
    keys = (set(a) | set(b)) - set(skip)
    return sorted(k for k in keys if k not in a or k not in b or not _same(a[k], b[k]))


# --- on one local Ray, started once for these tests ------------------------------------------------
@pytest.fixture(scope="class")
def engine():
    """One local Ray for the tests of a class (torn down before the cluster test starts)."""
    with fleet.Engine(workers=2) as eng:
        yield eng


class TestOnOneLocalRay:
    def test_resume_audits_only_changed_bags(self, engine, tmp_path):
        _resume(engine, tmp_path)

    def test_timeout_and_worker_death_are_rows_and_the_run_goes_on(self, engine, tmp_path):
        _timeout_and_death(engine, tmp_path)

    def test_a_worker_keeps_its_models_between_bags(self, engine, tmp_path):
        _worker_models(engine, tmp_path)


def _worker_models(engine, tmp_path):
    """Six bags of one robot on two reused workers: on each worker, every bag after its first
    takes the model from the worker's cache (one lookup per bag, a hit)."""
    cfg = fleet.FleetConfig(report=False)
    jobs = []
    for k in range(6):
        b = write_bag(tmp_path / "bags", BagSpec(f"m{k}", "planar_2link", 0.2, start_s=k))
        jobs.append(fleet.BagJob(str(b), fleet.bag_id(b), str(tmp_path / "out"), cfg,
                                 fleet.config_hash(cfg)))

    def probe(job):  # pickled by value: runs in the worker
        import os as _os

        from dyn_node.fleet.engine import audit_bag, worker_model_cache

        before = worker_model_cache().hits
        outcome = audit_bag(job)
        outcome.row["probe"] = (_os.getpid(), worker_model_cache().hits - before)
        return outcome

    outcomes = fleet.run_jobs(engine, jobs, fn=probe)
    assert [o.row["exit_category"] for o in outcomes] == ["ok"] * 6
    per_worker: dict[int, list[int]] = {}
    for o in outcomes:  # jobs order: a worker takes its bags in that order, one at a time
        pid, hits = o.row["probe"]
        per_worker.setdefault(pid, []).append(hits)
    assert max(len(h) for h in per_worker.values()) >= 2, per_worker  # workers were reused
    assert all(h[1:] == [1] * (len(h) - 1) for h in per_worker.values()), per_worker


def _flat(tree, prefix=""):
    """{dotted path: leaf} of a JSON tree, for field-by-field comparison."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _flat(sub, f"{prefix}{key}.").items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in _flat(sub, f"{prefix}{i}.").items()}
    return {prefix.rstrip("."): tree}


def test_a_worker_reuses_its_model_and_the_evidence_is_unchanged(tmp_path, monkeypatch):
    """audit_bag in one process, as a worker runs it: the second Panda bag takes the model the
    first built (no second build), the UR5 bag builds its own, and every evidence record equals,
    field by field, that of an uncached audit of the bag alone (dyn-audit builds per run)."""
    from dyn_node.core.robot import model_source
    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    builds: list[dict] = []
    real = model_source.load_model
    monkeypatch.setattr(model_source, "load_model", lambda **kw: builds.append(kw) or real(**kw))
    monkeypatch.setattr(fleet, "_MODEL_CACHE", None)  # a fresh worker
    specs = [BagSpec("w_panda_a", "panda", 0.4, spike=(0.1, 0.2), trajectories=(True,)),
             BagSpec("w_panda_b", "panda", 0.6, trajectories=(False,), start_s=10),
             BagSpec("w_ur5", "ur5", 0.4, start_s=20)]
    cfg = fleet.FleetConfig(report=False)
    counts, jobs = [], []
    for s in specs:
        b = write_bag(tmp_path / "bags", s)
        job = fleet.BagJob(str(b), fleet.bag_id(b), str(tmp_path / "out"), cfg, fleet.config_hash(cfg))
        assert fleet.audit_bag(job).row["verdict"] != "error", s.name
        cache = fleet.worker_model_cache()
        counts.append((cache.hits, cache.misses, len(builds)))
        jobs.append(job)
    assert counts == [(0, 1, 1), (1, 1, 1), (1, 2, 2)]  # (hits, misses, models built) after each bag
    for job in jobs:
        alone = tmp_path / "alone" / job.bag_id
        fresh = run_audit(AuditOptions(bag=job.path, out=str(alone), progress=False, report=False))
        mine = _flat(_strip(json.loads((job.out_dir / "evidence.json").read_text())))
        theirs = _flat(_strip(json.loads((alone / "evidence.json").read_text())))
        assert mine.keys() == theirs.keys() and len(mine) > 100
        assert [k for k in mine if not _same(mine[k], theirs[k])] == [], job.path
        assert fresh.exit_code == json.loads((job.out_dir / fleet.STATE_FILE).read_text())["row"]["exit_code"]
    assert len(builds) == 2 + len(jobs)  # the uncached audits each built their own


def _resume(engine, tmp_path):
    specs = [BagSpec(f"r{k}", ("panda", "ur5", "planar_2link")[k % 3], 0.4, start_s=k) for k in range(5)]
    root = tmp_path / "bags"
    for s in specs:
        write_bag(root, s)
    listing = tmp_path / "bags.txt"  # a list of bag paths is a ROOT too (relative to the list)
    listing.write_text("# nightly\n" + "".join(f"bags/{s.name}\n" for s in specs[:4]))
    out = tmp_path / "out"
    first = fleet.run_fleet([str(listing), str(root / "r4")], out, engine=engine, progress=False)
    assert [r["resumed"] for r in first.rows] == [False] * 5
    mtimes = {r["bag_id"]: (out / r["evidence"]).stat().st_mtime_ns for r in first.rows}
    # r1 changes (re-recorded, longer), r5 is new, the rest are untouched
    shutil.rmtree(root / "r1")
    write_bag(root, BagSpec("r1", "ur5", 0.8, spike=(0.1, 0.2), start_s=1))
    write_bag(root, BagSpec("r5", "panda", 0.4, start_s=5))
    second = fleet.run_fleet([str(root)], out, engine=engine, resume=True, progress=False)
    by = {Path(r["path"]).name: r for r in second.rows}
    assert {n for n, r in by.items() if not r["resumed"]} == {"r1", "r5"}
    assert by["r1"]["exit_category"] == "violations" and by["r1"]["joint_states"] == 400
    for r in first.rows:
        name = Path(r["path"]).name
        if name != "r1":
            assert (out / r["evidence"]).stat().st_mtime_ns == mtimes[r["bag_id"]]
            assert _differing(by[name], r, skip=("resumed",)) == []
    assert second.exit_code == 1
    # another configuration (a limits file) invalidates every bag's evidence
    lim = tmp_path / "lim.yaml"
    lim.write_text("joint_limits: {}\n")
    h0 = fleet.config_hash(fleet.FleetConfig())
    h1 = fleet.config_hash(fleet.FleetConfig(limits=str(lim)))
    lim.write_text("joint_limits:\n  panda_joint1:\n    has_effort_limits: true\n    max_effort: 1.0\n")
    assert len({h0, h1, fleet.config_hash(fleet.FleetConfig(limits=str(lim)))}) == 3


# --- isolation: timeouts and dying workers ------------------------------------------------------
def _listening_addresses(pids: set[int]) -> set[str]:
    """Local addresses of the TCP sockets in LISTEN state owned by ``pids``."""
    inodes: set[str] = set()
    for pid in pids:
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    addrs = set()
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A" or f[9] not in inodes:
                continue
            hexip = f[1].split(":")[0]
            raw = bytes.fromhex(hexip)
            if v6:
                raw = b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))
                import ipaddress

                ip = ipaddress.IPv6Address(raw)
                addrs.add(str(ip.ipv4_mapped or ip))
            else:
                addrs.add(".".join(str(b) for b in raw[::-1]))
    return addrs


def _descendants(root: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = set(), [root]
    while todo:
        p = todo.pop()
        for c in children.get(p, []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


def _assert_loopback_only() -> None:
    import ray

    pids = _descendants(os.getpid()) | {os.getpid()}
    addrs = _listening_addresses(pids)
    assert addrs and addrs <= {"127.0.0.1"}, addrs
    assert {n["NodeManagerAddress"] for n in ray.nodes() if n["Alive"]} == {"127.0.0.1"}


def _timeout_and_death(engine, tmp_path):
    specs = [BagSpec(n, "planar_2link", 0.3, start_s=k)
             for k, n in enumerate(("hang", "die_once", "die_always", "fine"))]
    root = tmp_path / "bags"
    jobs = []
    cfg = fleet.FleetConfig(report=False)
    for s in specs:
        b = write_bag(root, s)
        jobs.append(fleet.BagJob(str(b), fleet.bag_id(b), str(tmp_path / "out"), cfg,
                                 fleet.config_hash(cfg)))
    marks = str(tmp_path)

    def flaky(job):  # pickled by value: runs in the worker
        import os as _os
        import threading as _threading
        from pathlib import Path as _P

        from dyn_node.fleet.engine import audit_bag

        name = _P(job.path).name
        with open(_P(marks) / f"{name}.attempts", "a") as fh:
            fh.write("x")
        attempts = (_P(marks) / f"{name}.attempts").read_text().count("x")
        if name == "fine":  # the worker's thread settings
            (_P(marks) / "env.json").write_text(__import__("json").dumps(
                {k: _os.environ.get(k) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS",
                                                  "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}))
        if name == "hang":
            _threading.Event().wait(60)  # hangs past the limit: one that does not stop it fails below
        if name == "die_always" or (name == "die_once" and attempts == 1):
            _os._exit(7)
        return audit_bag(job)

    t0 = time.monotonic()
    _assert_loopback_only()
    # the limit counts from when a worker takes the bag: a retried bag's second worker has to
    # start (a few seconds on a loaded machine) within it
    outcomes = fleet.run_jobs(engine, jobs, bag_timeout_s=10.0, fn=flaky)
    wall = time.monotonic() - t0
    rows = {Path(o.row["path"]).name: o.row for o in outcomes}
    assert (rows["hang"]["exit_category"], rows["hang"]["error_code"]) == ("timeout", "timeout")
    assert rows["hang"]["audit_s"] >= 10.0 and wall < 120
    assert (rows["die_always"]["exit_category"], rows["die_always"]["error_code"]) == ("crashed", "worker_died")
    assert (tmp_path / "die_always.attempts").read_text() == "xx"  # Ray retried it exactly once
    assert (tmp_path / "die_once.attempts").read_text() == "xx"
    assert rows["die_once"]["exit_category"] == rows["fine"]["exit_category"] == "ok"
    assert fleet.fleet_exit_code([o.row for o in outcomes]) == 3  # no violations, some not audited
    assert json.loads((tmp_path / "env.json").read_text()) == fleet.WORKER_ENV


def test_exit_codes_of_a_fleet():
    def rows(*codes):
        return [{"exit_code": c} for c in codes]
    assert fleet.fleet_exit_code(rows(0, 0)) == 0
    assert fleet.fleet_exit_code(rows(0, 3)) == 3
    assert fleet.fleet_exit_code(rows(0, 2)) == 3
    assert fleet.fleet_exit_code(rows(1, 3, 2)) == 1
    assert fleet.fleet_exit_code(rows(2, 2)) == 2
    assert fleet.fleet_exit_code(rows()) == 2


def test_unusable_arguments_exit_2_one_line(tmp_path, capsys):
    assert fleet.main([str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dyn-fleet: error:") and err.count("\n") == 1 and "does not exist" in err
    (tmp_path / "empty").mkdir()
    assert fleet.main([str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "no bags found" in capsys.readouterr().err


# --- a two-node cluster on this machine -----------------------------------------------------------
def test_two_node_cluster_gives_identical_rows(fleet_run, tmp_path):
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "node_ip_address": "127.0.0.1", "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes()
        out = tmp_path / "out"
        res = fleet.run_fleet([str(fleet_run["root"] / "bags")], out, address=cluster.address,
                              progress=False)
        ray.init(address=cluster.address, log_to_driver=False)
        try:
            assert len([n for n in ray.nodes() if n["Alive"]]) == 2
            _assert_loopback_only()
        finally:
            ray.shutdown()
    finally:
        cluster.shutdown()
    assert res.exit_code == fleet_run["code"]
    assert len({r["node"] for r in res.rows if r["node"]}) == 2  # both nodes audited bags
    mine = {r["path"]: r for r in fleet_run["rows"]}
    for r in res.rows:
        assert _differing(r, mine[r["path"]], skip=VOLATILE_ROW) == [], r["path"]
        if r["evidence"]:
            assert _strip(json.loads((out / r["evidence"]).read_text())) == _strip(
                json.loads((fleet_run["out"] / r["evidence"]).read_text()))


def test_module_runs_as_python_m(tmp_path):
    import subprocess

    res = subprocess.run([sys.executable, "-m", "dyn_node.fleet.engine", "--version"], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.startswith("dyn-fleet ")
    assert "rclpy" not in subprocess.run(
        [sys.executable, "-c", "import sys, dyn_node.fleet.engine, dyn_node.fleet.report; "
         "print(' '.join(sorted(m for m in sys.modules if m.startswith('rclpy'))))"],
        capture_output=True, text=True, timeout=60).stdout


def test_non_finite_numbers_of_the_record_stay_non_finite(fleet_run):
    """The evidence record writes inf as "inf" (JSON has no inf): the row keeps it infinite."""
    r = fleet_run["by_name"]["planar_fast"]
    rec = json.loads((fleet_run["out"] / r["evidence"]).read_text())
    job = fleet.BagJob(r["path"], r["bag_id"], str(fleet_run["out"]), fleet.FleetConfig(), r["config_hash"])
    assert math.isfinite(fleet.row_from_record(job, rec, 1, "").row["worst_time_scale"])
    bad = next(t for t in rec["outputs"]["trajectories"] if not t["feasible"])
    bad["time_scale"] = "inf"
    assert fleet.row_from_record(job, rec, 1, "").row["worst_time_scale"] == math.inf
    rec["outputs"]["trajectories"] = []
    assert math.isnan(fleet.row_from_record(job, rec, 1, "").row["worst_time_scale"])
