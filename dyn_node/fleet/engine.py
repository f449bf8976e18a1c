"""dyn-fleet: audit many bags as Ray tasks and answer for the fleet.

Every bag is one Ray task running :func:`dyn_node.audit.pipeline.run_audit`, the pure audit ``dyn-audit``
runs; the driver only schedules, stops tasks that overrun, and writes the Parquet tables and
fleet.html. Options, isolation, resume, the tables and exit codes: docs/fleet.md. This
module never imports rclpy; Ray is imported only when the engine starts.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import shutil
import sys
import time
from collections import deque
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Sequence

from dyn_node import __version__
from dyn_node.audit.cli import add_audit_options, run_command
from dyn_node.errors import FleetError
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS, exit_code
from dyn_node.fleet import cleanup
from dyn_node.fleet.rows import (CRASHED, JOINT_COLUMNS, LIVE_KINDS, OK, PARTIAL, ROW_COLUMNS,  # noqa: F401
                                 ROW_FORMAT, TIMEOUT, TRAJ_KINDS, UNUSABLE, VIOLATIONS, BagJob,
                                 BagOutcome, FleetConfig, error_outcome, partial_note,
                                 row_from_record, trajectories_line)

if TYPE_CHECKING:
    from dyn_node.core.robot.model_source import ModelCache

STATE_FILE = "fleet_row.json"
#: One BLAS / Numba / OpenMP thread per worker: the workers are the parallelism.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1"}
LOOPBACK = "127.0.0.1"
HASH_BLOCK = 1 << 20


def _file_sha256(path: Path | None) -> str:
    if path is None:
        return ""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(HASH_BLOCK), b""):
            h.update(block)
    return h.hexdigest()


def config_hash(cfg: FleetConfig) -> str:
    """Changes when anything that can change a bag's evidence changes: the options, the contents
    of the override files, dyn_node's version and the row format."""
    def content(p: str) -> str:
        return _file_sha256(Path(p)) if p and Path(p).is_file() else p
    doc = {"row_format": ROW_FORMAT, "dyn_node": __version__, "robot_model": cfg.robot_model,
           "robot_description": content(cfg.robot_description), "limits": content(cfg.limits),
           "gap_threshold_s": cfg.gap_threshold_s, "topics": sorted(cfg.topics), "report": cfg.report}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def bag_files(path: Path) -> list[Path]:
    """The files whose bytes make up a bag: a rosbag2 directory's regular files, or the file."""
    if path.is_dir():
        return sorted(f for f in path.iterdir() if f.is_file())
    return [path]


def content_hash(path: Path) -> str:
    """SHA-256 over the bag's files: each file's name, size and bytes, in name order."""
    h = hashlib.sha256()
    for f in bag_files(path):
        h.update(f"{f.name}\0{f.stat().st_size}\0".encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(HASH_BLOCK), b""):
                h.update(block)
    return h.hexdigest()


def bag_id(path: Path) -> str:
    """The bag's name (directory or file stem, made path-safe) and a hash of its absolute path,
    so two bags with the same name in different directories never share outputs."""
    name = path.name[:-5] if path.name.endswith(".mcap") else path.name
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "bag"
    return f"{safe[:80]}-{hashlib.sha1(str(path).encode()).hexdigest()[:10]}"


# --- discovery ---------------------------------------------------------------------------------
def _walk(root: Path, skip: Path | None) -> Iterable[Path]:
    for d, dirs, files in os.walk(root):
        here = Path(d)
        if skip is not None and (here == skip or skip in here.parents):
            dirs[:] = []
            continue
        if "metadata.yaml" in files:  # a rosbag2 directory: the bag, nothing inside it is another
            dirs[:] = []
            yield here
            continue
        # a directory named like a bag file is an input too: it gets a row (with its error)
        named = sorted(x for x in dirs if x.endswith(".mcap"))
        dirs[:] = sorted(x for x in dirs if not x.endswith(".mcap"))
        yield from sorted([here / x for x in named] + [here / f for f in files if f.endswith(".mcap")])


def discover(roots: Sequence[str], *, skip: Path | None = None) -> list[Path]:
    """Bags under ``roots``: directories are searched recursively for rosbag2 directories (with
    metadata.yaml) and loose .mcap files; any other file is a list of bag paths, one per line
    (blank lines and ``#`` comments skipped; relative paths are relative to the list's directory).
    A listed path that does not exist is kept: it becomes a row with its error."""
    found: dict[str, Path] = {}
    skip = skip.resolve() if skip is not None else None
    for r in roots:
        root = Path(r).expanduser()
        if root.is_dir() and not (root.suffix == ".mcap" and not (root / "metadata.yaml").exists()):
            bags: Iterable[Path] = _walk(root.resolve(), skip)
        elif root.suffix == ".mcap" and (root.is_file() or root.is_dir()):
            bags = [root.resolve()]
        elif root.is_file():
            bags = [(root.parent / line.strip()).resolve() if not Path(line.strip()).is_absolute()
                    else Path(line.strip())
                    for line in root.read_text().splitlines()
                    if line.strip() and not line.lstrip().startswith("#")]
        else:
            raise FleetError(f"{r} does not exist", code="not_found")
        for b in bags:
            found.setdefault(str(b), b)
    return [found[k] for k in sorted(found)]


# --- one bag (runs inside a Ray worker) --------------------------------------------------------
def _state_path(job: BagJob) -> Path:
    return job.out_dir / STATE_FILE


def _load_state(job: BagJob) -> dict | None:
    try:
        state = json.loads(_state_path(job).read_text())
    except (OSError, ValueError):
        return None
    return state if isinstance(state, dict) and state.get("row_format") == ROW_FORMAT else None


def _save_state(job: BagJob, outcome: BagOutcome) -> None:
    p = _state_path(job)
    tmp = p.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"row_format": ROW_FORMAT, "row": outcome.row, "joints": outcome.joints},
                              allow_nan=True))
    tmp.replace(p)


def _node_id() -> str:
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else ""
    except Exception:  # noqa: BLE001 - informational only
        return ""


_MODEL_CACHE: "ModelCache | None" = None
MODEL_CACHE_SIZE = 8  # robot variants a worker keeps built (about 50 kB each for the Panda)


def worker_model_cache() -> "ModelCache":
    """This process's models: a Ray worker runs task after task (one at a time), so the second
    bag of a robot reuses the model the first one built."""
    global _MODEL_CACHE
    if _MODEL_CACHE is None:
        from dyn_node.core.robot.model_source import ModelCache

        _MODEL_CACHE = ModelCache(MODEL_CACHE_SIZE)
    return _MODEL_CACHE


def audit_bag(job: BagJob) -> BagOutcome:
    """Audit one bag exactly as ``dyn-audit`` does (same :func:`run_audit`, same options) and make
    its rows. Never raises for a bad bag: every failure is a row with its error."""
    from dyn_node.audit.options import AuditError, AuditOptions
    from dyn_node.audit.pipeline import run_audit
    from dyn_node.bag.reader import BagError
    from dyn_node.errors import DynNodeError

    wall0 = time.perf_counter()
    path = Path(job.path)
    try:
        digest = content_hash(path)
    except OSError as exc:
        return _finish(error_outcome(job, UNUSABLE, "bag_unreadable",
                                     f"bag {path} is unreadable: {exc.strerror or exc}"), wall0)
    if job.resume:
        state = _load_state(job)
        if (state and state["row"]["content_hash"] == digest
                and state["row"]["config_hash"] == job.config_hash):
            row = dict(state["row"], resumed=True)
            return BagOutcome(row, state["joints"])
    shutil.rmtree(job.out_dir, ignore_errors=True)  # no evidence of an earlier run survives
    job.out_dir.mkdir(parents=True, exist_ok=True)
    cfg = job.config
    opts = AuditOptions(bag=job.path, robot_description=cfg.robot_description,
                        robot_model=cfg.robot_model, limits=cfg.limits, out=str(job.out_dir),
                        topics=cfg.topics, gap_threshold_s=cfg.gap_threshold_s, progress=False,
                        report=cfg.report, model_cache=worker_model_cache(), threads=1)
    try:
        res = run_audit(opts)
    except (AuditError, BagError, DynNodeError) as exc:
        outcome = error_outcome(job, UNUSABLE, getattr(exc, "code", "") or type(exc).__name__, str(exc),
                                content_hash=digest)
    except OSError as exc:
        return _finish(error_outcome(job, UNUSABLE, "os_error",
                                     f"{exc.strerror or exc}: {exc.filename or job.path}",
                                     content_hash=digest), wall0)
    except Exception as exc:  # noqa: BLE001 - a crash in one bag must not end the fleet run
        return _finish(error_outcome(job, CRASHED, "crash", f"{type(exc).__name__}: {exc}",
                                     content_hash=digest), wall0)
    else:
        outcome = row_from_record(job, res.record, res.exit_code, digest)
    _finish(outcome, wall0)
    if not outcome.row["audited_utc"]:
        from dyn_node.audit.evidence import utc_now

        outcome.row["audited_utc"] = utc_now()
    _save_state(job, outcome)  # only outcomes the audit decided: timeouts and crashes are redone
    return outcome


def _finish(outcome: BagOutcome, wall0: float) -> BagOutcome:
    outcome.row["audit_s"] = time.perf_counter() - wall0
    outcome.row["node"] = _node_id()
    return outcome


# --- the engine ----------------------------------------------------------------------------------
def _ray_env(*, local: bool) -> None:
    """Before Ray is imported: no usage statistics; for the local runtime, keep 127.0.0.1 as the
    node address (Ray otherwise replaces a loopback address by the machine's routable one). A
    driver joining a remote cluster must keep its routable address, so that stays Ray's."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    if local:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


class Engine:
    """Ray, started in-process on 127.0.0.1 (``address=""``) or joined (``auto``, ``ray://``,
    ``host:port``); ``slots``: tasks that run at once (the cluster's CPUs)."""

    def __init__(self, *, address: str = "", workers: int = 0):
        self.address, self.workers = address, workers or usable_cores()
        self.started_s = 0.0
        self.slots = self.workers
        self.temp_dir: Path | None = None   # Ray's session files (local Ray only), removed at exit
        self._baseline: set[int] = set()    # processes that were there before Ray started
        self.ray: Any = None

    def __enter__(self) -> "Engine":
        try:
            return self._start()
        except BaseException:  # Ctrl-C while Ray starts too: nothing it started may be left
            self._stop()
            raise

    def _start(self) -> "Engine":
        import logging

        _ray_env(local=not self.address)
        t0 = time.perf_counter()
        try:
            import ray
        except ImportError as exc:  # pragma: no cover - ray is a pinned dependency
            raise FleetError(f"Ray is not installed ({exc}): pip install -r requirements.txt",
                             code="ray_missing") from None
        self.ray = ray
        if not self.address:
            # Ray reads this setting once, at import: refuse before anything binds elsewhere
            from ray._private import ray_constants

            if getattr(ray_constants, "ENABLE_RAY_CLUSTER", False):
                raise FleetError("Ray was imported before dyn_node.fleet.engine could keep it on "
                                 f"{LOOPBACK}: set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 before "
                                 "importing ray", code="ray_not_loopback")
        common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
                      configure_logging=True)
        try:
            if self.address:  # the workers of other nodes get the thread settings per job
                ray.init(address=self.address, runtime_env={"env_vars": dict(WORKER_ENV)}, **common)
            else:  # inherited by the raylet, so its pre-started workers can take the first bags
                self._baseline = {p for p, _s in cleanup.descendants()}
                self.temp_dir = cleanup.make_temp_dir()
                with _environ(WORKER_ENV):
                    ray.init(num_cpus=self.workers, _node_ip_address=LOOPBACK,
                             _temp_dir=str(self.temp_dir), **common)
        except Exception as exc:  # noqa: BLE001 - Ray's own errors are many; one line for the user
            raise FleetError(f"cannot start Ray{' at ' + self.address if self.address else ''}: "
                             f"{type(exc).__name__}: {exc}", code="ray_start") from None
        if not self.address:
            ip = ray.util.get_node_ip_address()
            if ip != LOOPBACK:
                raise FleetError(f"local Ray bound to {ip}, not {LOOPBACK}: set "
                                 "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 before Ray is imported",
                                 code="ray_not_loopback")
        self.slots = max(1, int(ray.cluster_resources().get("CPU", self.workers)))
        self.started_s = time.perf_counter() - t0
        self.remote = ray.remote(num_cpus=1, max_retries=1, retry_exceptions=False,
                                 max_calls=0)(_run_job)
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop()

    def _stop(self) -> None:
        """Shut Ray down; a local Ray's processes still running after that are ended (Ctrl-C
        leaves its agents otherwise running for a minute) and its session files removed."""
        local = self.temp_dir is not None
        # listed before the shutdown: once the raylet is gone its agents are no longer ours
        started = cleanup.ray_processes(self._baseline) if local else []
        if self.ray is not None:
            self.ray.shutdown()
        if local:
            cleanup.end_processes(started)
            cleanup.remove_temp_dir(self.temp_dir)
            self.temp_dir = None


@contextmanager
def _environ(values: dict[str, str]) -> Iterator[None]:
    """``values`` set in os.environ for the block (child processes started in it keep them)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def _run_job(job: BagJob, fn: Callable[[BagJob], BagOutcome] | None = None) -> BagOutcome:
    """The task body: ``fn`` (default :func:`audit_bag`) on one bag."""
    return (fn or audit_bag)(job)


def _ray_failure(job: BagJob, exc: BaseException) -> BagOutcome:
    import ray.exceptions as rx

    if isinstance(exc, (rx.WorkerCrashedError, rx.NodeDiedError, rx.ActorDiedError)):
        return error_outcome(job, CRASHED, "worker_died",
                             f"the worker died twice (retried once): {type(exc).__name__}")
    if isinstance(exc, rx.OutOfMemoryError):
        return error_outcome(job, CRASHED, "out_of_memory", f"killed for memory: {str(exc).strip()[:300]}")
    if isinstance(exc, rx.TaskCancelledError):
        return error_outcome(job, TIMEOUT, "timeout", "the task was cancelled")
    return error_outcome(job, CRASHED, "task_error", f"{type(exc).__name__}: {str(exc).strip()[:300]}")


def run_jobs(engine: Engine, jobs: Sequence[BagJob], *, bag_timeout_s: float = 0.0,
             progress: "Progress | None" = None,
             fn: Callable[[BagJob], BagOutcome] | None = None) -> list[BagOutcome]:
    """Run the jobs on the engine; at most ``engine.slots`` in flight, so a task's time limit
    counts from when a free worker takes it. Results in ``jobs`` order."""
    ray = engine.ray
    results: dict[int, BagOutcome] = {}
    queue = deque(enumerate(jobs))
    flight: dict[Any, tuple[int, float]] = {}
    fn_ref = ray.put(fn) if fn is not None else None

    def done(i: int, outcome: BagOutcome) -> None:
        results[i] = outcome
        if progress is not None:
            progress.add(outcome.row)

    while queue or flight:
        while queue and len(flight) < engine.slots:
            i, job = queue.popleft()
            flight[engine.remote.remote(job, fn_ref)] = (i, time.monotonic())
        wait_s = 0.5
        if bag_timeout_s > 0:
            first = min(t for _, t in flight.values())
            wait_s = max(0.0, min(wait_s, first + bag_timeout_s - time.monotonic()))
        ready, _ = ray.wait(list(flight), num_returns=1, timeout=wait_s)
        for ref in ready:
            i, _t = flight.pop(ref)
            try:
                done(i, ray.get(ref))
            except Exception as exc:  # noqa: BLE001 - Ray's task failures become rows
                done(i, _ray_failure(jobs[i], exc))
        if bag_timeout_s > 0:
            now = time.monotonic()
            for ref, (i, t) in list(flight.items()):
                if now - t >= bag_timeout_s:
                    ray.cancel(ref, force=True)  # kills the worker process; Ray starts another
                    del flight[ref]
                    done(i, error_outcome(jobs[i], TIMEOUT, "timeout",
                                          f"stopped after the bag time limit ({bag_timeout_s:g} s)",
                                          audit_s=now - t))
        if progress is not None:
            progress.draw()
    return [results[i] for i in range(len(jobs))]


# --- progress ----------------------------------------------------------------------------------
class Progress:
    """bags done / total, ETA and failures on stderr: a redrawn line on a terminal, otherwise a
    line every ``period_s`` and at the end."""

    def __init__(self, total: int, *, stream: Any = None, enabled: bool = True, period_s: float = 5.0):
        self.total, self.stream, self.on = total, stream or sys.stderr, enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.period_s = period_s
        self.done = self.failed = self.violations = self.resumed = 0
        self.t0 = time.monotonic()
        self.last = -math.inf

    def add(self, row: dict) -> None:
        self.done += 1
        self.resumed += bool(row.get("resumed"))
        self.failed += row["exit_category"] in (UNUSABLE, TIMEOUT, CRASHED)
        self.violations += row["exit_category"] == VIOLATIONS

    def line(self) -> str:
        el = time.monotonic() - self.t0
        audited = self.done - self.resumed
        left = self.total - self.done
        eta = (el / audited * left) if audited and left else (0.0 if not left else math.nan)
        eta_s = "--:--" if math.isnan(eta) else f"{int(eta // 60):d}:{int(eta % 60):02d}"
        frac = self.done / self.total if self.total else 1.0
        bar = "#" * int(frac * 24)
        return (f"dyn-fleet [{bar:<24}] {self.done}/{self.total} bags  ETA {eta_s}  "
                f"{self.violations} with violations  {self.failed} failed"
                + (f"  {self.resumed} unchanged" if self.resumed else ""))

    def draw(self, final: bool = False) -> None:
        if not self.on:
            return
        now = time.monotonic()
        if self.tty:
            if final or now - self.last >= 0.2:
                self.stream.write("\r" + self.line() + ("\n" if final else ""))
                self.stream.flush()
                self.last = now
        elif final or now - self.last >= self.period_s:
            self.stream.write(self.line() + "\n")
            self.stream.flush()
            self.last = now


# --- tables --------------------------------------------------------------------------------------
def _arrow_schema(columns: list[tuple[str, str, str, str]]):
    import pyarrow as pa

    types = {"string": pa.string(), "int8": pa.int8(), "int32": pa.int32(), "int64": pa.int64(),
             "float64": pa.float64(), "bool": pa.bool_()}
    return pa.schema([pa.field(n, types[t], metadata={"unit": u, "description": d})
                      for n, t, u, d in columns])


def write_table(rows: list[dict], columns: list[tuple[str, str, str, str]], path: Path) -> Path:
    """Rows to Parquet with the documented schema (column units in the field metadata)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = _arrow_schema(columns)
    table = pa.Table.from_pylist([{n: r.get(n) for n, *_ in columns} for r in rows], schema=schema)
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(table, tmp)
    tmp.replace(path)
    return path


def fleet_exit_code(rows: Sequence[dict]) -> int:
    """0 all feasible, 1 violations found (wins over 3), 3 some bags not (fully) audited and no
    violations, 2 nothing usable (no bag audited)."""
    codes = [r["exit_code"] for r in rows]
    return exit_code(violations=EXIT_VIOLATIONS in codes,
                     partial=any(c in (EXIT_PARTIAL, EXIT_UNUSABLE) for c in codes),
                     unusable=not codes or all(c == EXIT_UNUSABLE for c in codes))


@dataclass
class FleetResult:
    rows: list[dict]
    joints: list[dict]
    exit_code: int
    out_dir: Path
    files: list[Path]
    ray_start_s: float
    wall_s: float


def run_fleet(roots: Sequence[str], out: str | Path, *, config: FleetConfig = FleetConfig(),
              address: str = "", workers: int = 0, resume: bool = False,
              bag_timeout_s: float = 1800.0, progress: bool = True,
              fn: Callable[[BagJob], BagOutcome] | None = None,
              engine: Engine | None = None) -> FleetResult:
    """Discover, audit every bag on Ray, write the tables and the page. ``fn`` replaces the
    per-bag function (tests inject crashes and hangs with it); ``engine``: an engine already
    started (left running), instead of one started and shut down here."""
    wall0 = time.perf_counter()
    out_dir = Path(out).resolve()
    bags = discover(roots, skip=out_dir)
    if not bags:
        raise FleetError("no bags found under " + ", ".join(roots), code="no_bags")
    for f in (config.robot_description, config.limits):
        if f and not Path(f).is_file():
            raise FleetError(f"{f} does not exist", code="not_found")
    config = replace(config, robot_description=str(Path(config.robot_description).resolve())
                     if config.robot_description else "",
                     limits=str(Path(config.limits).resolve()) if config.limits else "")
    chash = config_hash(config)
    (out_dir / "bags").mkdir(parents=True, exist_ok=True)
    jobs = [BagJob(str(b), bag_id(b), str(out_dir), config, chash, resume) for b in bags]
    prog = Progress(len(jobs), enabled=progress)
    with nullcontext(engine) if engine is not None else Engine(address=address, workers=workers) as eng:
        prog.draw()
        outcomes = run_jobs(eng, jobs, bag_timeout_s=bag_timeout_s, progress=prog, fn=fn)
    prog.draw(final=True)
    rows = [o.row for o in outcomes]
    joints = [j for o in outcomes for j in o.joints]
    files = [write_table(rows, ROW_COLUMNS, out_dir / "fleet.parquet"),
             write_table(joints, JOINT_COLUMNS, out_dir / "fleet_joints.parquet")]
    code = fleet_exit_code(rows)
    from dyn_node.fleet.report import write_fleet_report

    files.append(write_fleet_report(rows, joints, out_dir, exit_code=code))
    return FleetResult(rows, joints, code, out_dir, files, eng.started_s,
                       time.perf_counter() - wall0)


# --- command line --------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dyn-fleet", description="Audit many bags (each exactly as dyn-audit would) on Ray; "
        "write DIR/fleet.parquet, DIR/fleet_joints.parquet, DIR/fleet.html and DIR/bags/<id>/. "
        "Exit 0: all feasible, 1: violations found, 3: some bags not (fully) audited and no "
        "violations, 2: nothing usable.")
    p.add_argument("roots", nargs="+", metavar="ROOT",
                   help="directory searched recursively for bags (rosbag2 directories, .mcap files), "
                        "a .mcap file, or a text file listing bag paths")
    p.add_argument("--out", metavar="DIR", required=True, help="output directory")
    p.add_argument("--address", default="", metavar="ADDR",
                   help="existing Ray cluster: auto, ray://host:port or host:port (default: start "
                        "Ray in this process on 127.0.0.1)")
    p.add_argument("--workers", type=int, default=0, metavar="N",
                   help="CPUs of the local Ray (default: the usable cores); ignored with --address")
    p.add_argument("--resume", action="store_true",
                   help="skip bags whose content and configuration are unchanged since their evidence")
    p.add_argument("--bag-timeout", type=float, default=1800.0, metavar="S",
                   help="stop a bag's task after S seconds and report it (0: no limit; default 1800)")
    add_audit_options(p, every_bag=True)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--version", action="version", version=f"dyn-fleet {__version__}")
    return p


def _summary(res: FleetResult) -> str:
    n = len(res.rows)
    by = {c: sum(r["exit_category"] == c for r in res.rows)
          for c in (OK, VIOLATIONS, PARTIAL, UNUSABLE, TIMEOUT, CRASHED)}
    parts = [f"{by[c]} {c}" for c in by if by[c]]
    resumed = sum(bool(r["resumed"]) for r in res.rows)
    word = {EXIT_OK: "FEASIBLE", EXIT_VIOLATIONS: "VIOLATIONS", EXIT_PARTIAL: "PARTIAL",
            EXIT_UNUSABLE: "UNUSABLE"}[res.exit_code]
    return (f"{word}: {n} bags: " + ", ".join(parts) + partial_note(res.rows)
            + (f" ({resumed} unchanged, not re-audited)" if resumed else ""))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.workers < 0 or args.bag_timeout < 0 or not args.gap_threshold > 0:
        print("dyn-fleet: error: --workers and --bag-timeout must be >= 0, --gap-threshold > 0",
              file=sys.stderr)
        return EXIT_UNUSABLE
    cfg = FleetConfig(robot_model=args.robot_model, robot_description=args.robot_description,
                      limits=args.limits, gap_threshold_s=args.gap_threshold,
                      topics=tuple(args.topics), report=not args.no_report)
    work = partial(run_fleet, args.roots, args.out, config=cfg, address=args.address,
                   workers=args.workers, resume=args.resume, bag_timeout_s=args.bag_timeout,
                   progress=not args.quiet)
    return run_command("dyn-fleet", work, _print_result)


def _print_result(res: FleetResult) -> int:
    print(_summary(res))
    print(trajectories_line(res.rows))
    for r in res.rows:
        if r["exit_category"] in (UNUSABLE, TIMEOUT, CRASHED):
            print(f"  - {Path(r['path']).name}: {r['exit_category']}: {r['error']}")
    for f in res.files:
        print(f"{f.name + ':':<21} {f}")
    return res.exit_code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
