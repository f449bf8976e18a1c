"""dyn-audit's pass over a bag, its stages chained: read the configurations
(:mod:`.replay.config`), stream every message to the replay (:mod:`.replay.inputs`) and the
re-check (:mod:`.replay.recheck`), build the evidence and the verdict (:mod:`.sections`), write
evidence.json and the report."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from dyn_node.audit.evidence import utc_now
from dyn_node.audit.options import AuditOptions, AuditResult
from dyn_node.audit.replay.common import SeriesBins
from dyn_node.audit.replay.config import AuditSource, Configurator
from dyn_node.audit.replay.inputs import Replay
from dyn_node.audit.replay.recheck import Rechecker
from dyn_node.audit.replay.roles import Roles
from dyn_node.audit.sections import add_verdict, build_evidence, require_inputs
from dyn_node.bag.reader import BagReader, MessageDecoder


class Audit:
    """One pass over a bag, in stages: :meth:`read` (the bag and its configurations),
    :class:`Replay` (the inputs through the node's core), :class:`Rechecker` (the recorded outputs
    against the replayed ones), :func:`build_evidence`, :func:`add_verdict`. :meth:`run` chains
    them and returns the EvidenceRecord dict, the exit code and the plot series."""

    def __init__(self, opts: AuditOptions):
        self.opts = opts
        self.findings: list[str] = []
        self.decoder = MessageDecoder()

    def read(self) -> AuditSource:
        """Stage 1: open the bag and resolve the configurations to replay under."""
        return Configurator(self.opts, self.decoder, self.findings).read()

    def run(self) -> tuple[dict, int, SeriesBins | None]:
        """read → replay (with the re-check of the recorded outputs alongside) → evidence →
        verdict; returns the EvidenceRecord dict, the exit code and the plot series."""
        opts = self.opts
        started = utc_now()
        wall0 = time.perf_counter()
        source = self.read()
        reader = source.reader
        recheck = Rechecker(reader.known_topics(), self.decoder)
        replay = Replay(source.configurations, gap_threshold_s=opts.gap_threshold_s,
                        decoder=self.decoder, sink=recheck, threads=opts.threads)
        if source.model_source == "bag:topic" and len(source.configurations) > 1:
            replay.contact.without_model()  # the node's first core came with a later configuration
        roles = Roles(opts.topics)
        self.n_msgs = stream(reader, roles, replay, recheck, _Progress(reader, opts.progress))
        result = replay.finish()
        self.settings, self.model = result.settings, result.model
        self.contact_series = result.contact.series if result.contact is not None else None
        require_inputs(opts.bag, reader, result, source.first.model)
        rec = build_evidence(opts, source, roles, result, recheck.result())
        rec.started_utc = started
        code = add_verdict(rec, source, result, gap_threshold_s=opts.gap_threshold_s)
        rec.duration_s = time.perf_counter() - wall0
        rec.finished_utc = utc_now()
        return rec.to_dict(), code, result.live.series


def stream(reader: BagReader, roles: Roles, replay: Replay, recheck: Rechecker | None,
           progress: "_Progress | None" = None) -> int:
    """Every message of the bag in file order to the stage that takes its role; the number of
    messages read. The replay goes first: it answers an output's input before the output."""
    n_msgs = 0
    for m in reader.messages():
        n_msgs += 1
        if progress is not None and n_msgs & 1023 == 0:
            progress.update(n_msgs)
        role = roles.of(m)
        if role is None:
            continue
        if replay.feed(role, m) or recheck is None:
            continue
        recheck.output(role, m, replay.model)
    if progress is not None:
        progress.done(n_msgs)
    return n_msgs



class _Progress:
    """A one-line progress bar on stderr, only when stderr is a terminal (plain \\r updates)."""

    def __init__(self, reader: BagReader, enabled: bool | None):
        self.on = sys.stderr.isatty() if enabled is None else enabled
        self.reader = reader
        self.total = sum(f.stat().st_size for f in reader.files if f.exists()) or 1
        self.last = 0.0
        self.t0 = time.monotonic()

    def update(self, n: int, final: bool = False) -> None:
        if not self.on:
            return
        now = time.monotonic()
        if now - self.last < 0.2 and not final:
            return
        self.last = now
        # the summary section at the end of each file is not streamed: at the end, 100 %
        frac = 1.0 if final else min(self.reader.stats.bytes_read / self.total, 1.0)
        bar = "#" * int(frac * 30)
        rate = n / max(now - self.t0, 1e-9)
        sys.stderr.write(f"\rdyn-audit [{bar:<30}] {frac * 100:5.1f}%  {n} msgs  {rate:,.0f} msg/s")
        sys.stderr.flush()

    def done(self, n: int) -> None:
        if self.on:
            self.update(n, final=True)
            sys.stderr.write("\n")
            sys.stderr.flush()


def run_audit(opts: AuditOptions) -> AuditResult:
    """Run the audit and write evidence.json (+ report.html and PNGs) into ``opts.out``.
    Raises :class:`AuditError` / :class:`BagError` for unusable input."""
    import json

    wall0 = time.perf_counter()
    audit = Audit(opts)
    record, code, series = audit.run()
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    ev = out / "evidence.json"
    tmp = ev.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False, allow_nan=False))
    tmp.replace(ev)
    files = [ev]
    if opts.report:
        from dyn_node.audit.report import write_report

        files += write_report(record, series, audit.model, out, contact_series=audit.contact_series,
                              threads=opts.threads)
    return AuditResult(record, code, out, files, audit.n_msgs, time.perf_counter() - wall0)
