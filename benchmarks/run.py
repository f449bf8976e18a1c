"""`make bench`: run the selected sections, write bench_out/bench.json, regenerate the docs.

    python -m benchmarks.run                       # everything (under 10 minutes on 2 cores)
    python -m benchmarks.run --only dynamics,live  # some sections
    python -m benchmarks.run --quick               # smaller sizes, shorter windows

Sections not run keep their previous figures in bench.json (each section records when it was
measured). A subject that cannot run is recorded as "not available: <reason>", never a failure
of the whole run.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

from . import report
from .common import REPO, NotAvailable, machine_info, progress

SECTION_NAMES = ("dynamics", "live", "feasibility", "recording", "fleet", "services", "parsing", "retime", "gate",
                 "sim")
OPT_IN = ("libraries",)  # run only when named in --only; kept in bench.json, not rendered
ALIASES = {"audit": "recording", "memory": "live"}


def _section_runner(name: str):
    if name == "dynamics":
        from . import dynamics_bench as mod
    elif name == "live":
        from . import live_bench as mod
    elif name == "feasibility":
        from . import feasibility_bench as mod
    elif name == "fleet":
        from . import fleet_bench as mod
    elif name == "libraries":
        from . import libraries_bench as mod
    elif name == "services":
        from . import services_bench as mod
    elif name == "parsing":
        from . import parse_bench as mod
    elif name == "retime":
        from . import retime_bench as mod
    elif name == "gate":
        from . import gate_bench as mod
    elif name == "sim":
        from . import sim_bench as mod
    else:
        from . import recording_bench as mod
    return mod.run


def run_sections(names: list[str], quick: bool, smoke: bool = False) -> dict:
    out = {}
    for name in names:
        progress(name, "start")
        t0 = time.perf_counter()
        sec: dict = dict(measured_at=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), quick=quick,
                         smoke=smoke, loadavg_start=os.getloadavg()[0])
        try:
            sec["result"] = _section_runner(name)(quick=quick, smoke=smoke)
            sec["status"] = "ok"
        except NotAvailable as exc:
            sec["status"] = f"not available: {exc}"
        except Exception as exc:  # a broken subject must not hide the other sections' figures
            traceback.print_exc()
            sec["status"] = f"failed: {type(exc).__name__}: {exc}"
        sec["wall_s"] = time.perf_counter() - t0
        sec["loadavg_end"] = os.getloadavg()[0]
        progress(name, f"{sec['status']} ({sec['wall_s']:.1f} s)")
        out[name] = sec
    return out


def parse_only(text: str | None) -> list[str]:
    if not text:
        return list(SECTION_NAMES)
    names = []
    for raw in text.split(","):
        n = ALIASES.get(raw.strip(), raw.strip())
        if n not in SECTION_NAMES + OPT_IN:
            raise SystemExit(f"unknown section {raw!r}; choose from {', '.join(SECTION_NAMES + OPT_IN)}")
        if n not in names:
            names.append(n)
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", help=f"comma-separated sections: {','.join(SECTION_NAMES)}")
    ap.add_argument("--quick", action="store_true", help="smaller sizes and shorter windows")
    ap.add_argument("--render-only", action="store_true",
                    help="measure nothing: regenerate the docs and the summary section from bench.json")
    ap.add_argument("--smoke", action="store_true",
                    help="tiny sizes to check the harness runs (the test suite); figures meaningless")
    ap.add_argument("--out", default=str(REPO / "bench_out"), help="directory for bench.json")
    ap.add_argument("--docs", default=str(REPO / "docs" / "BENCHMARKS.md"),
                    help="generated markdown ('' to skip)")
    ap.add_argument("--summary", "--readme", dest="summary", default=str(REPO / "docs" / "performance.md"),
                    help="page whose BENCH markers are refreshed ('' to skip)")
    args = ap.parse_args(argv)
    names = parse_only(args.only)
    t0 = time.perf_counter()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path = out_dir / "bench.json"
    doc: dict = {"sections": {}}
    if json_path.exists():
        try:
            doc = json.loads(json_path.read_text())
            doc.setdefault("sections", {})
        except json.JSONDecodeError:
            doc = {"sections": {}}
    if args.render_only:
        if "machine" not in doc:
            raise SystemExit(f"{json_path} has no results to render; run without --render-only")
    else:
        progress("bench", "machine and versions")
        doc["machine"] = machine_info()
        doc["sections"].update(run_sections(names, args.quick, args.smoke))
        doc["last_run"] = dict(sections=names, quick=args.quick, smoke=args.smoke,
                               wall_s=time.perf_counter() - t0,
                               finished_at=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()))
        json_path.write_text(json.dumps(doc, indent=1, default=float))
    md = report.render(doc)
    if args.docs:
        Path(args.docs).parent.mkdir(parents=True, exist_ok=True)
        Path(args.docs).write_text(md)
    summary_done = False
    if args.summary:
        # the summary links the full page, relative to where the summary lives
        full = os.path.relpath(args.docs or REPO / "docs" / "BENCHMARKS.md", Path(args.summary).parent)
        summary_done = report.replace_between_markers(
            Path(args.summary), report.summary_md(doc, full_page=Path(full).as_posix()))
    print(md)
    print(f"\nraw figures: {json_path}" + (f"; docs: {args.docs}" if args.docs else "")
          + (f"; summary refreshed in {args.summary}" if summary_done
             else "; summary: no page with BENCH markers, untouched"))
    print(f"total wall time: {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
