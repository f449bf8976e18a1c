"""report.html: self-contained (no network), structure present, images embedded and equal to the PNGs."""
from __future__ import annotations

import base64
import json
import re
import sys
from html.parser import HTMLParser
from pathlib import Path

import jsonschema
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_audit import MS, T0, make_bag, trajectory_msg  # noqa: E402

from dyn_node.audit.bag_audit import AuditOptions, run_audit  # noqa: E402
from dyn_node.audit.evidence import schema  # noqa: E402
from dyn_node.audit.report import PNG_FILES  # noqa: E402


class Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        if data.strip():
            self.text.append(data.strip())


def parse(path: Path) -> tuple[str, Page]:
    html = path.read_text(encoding="utf-8")
    p = Page()
    p.feed(html)
    return html, p


def test_report_is_self_contained_and_has_every_section(tmp_path):
    trajs = [(100, trajectory_msg(T0 + 100 * MS)), (300, trajectory_msg(T0 + 300 * MS, scale=0.05))]
    bag = make_bag(tmp_path / "bag", n=800, effort_spike=(500, 520), drop=range(600, 700),
                   trajectories=trajs)
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out")))
    out = tmp_path / "out"
    rec = json.loads((out / "evidence.json").read_text())
    jsonschema.Draft202012Validator(schema()).validate(rec)
    assert res.exit_code == 1
    html, page = parse(out / "report.html")
    # nothing fetched from anywhere: every src/href is a data: URI or an in-page anchor
    for tag, attrs in page.tags:
        for k in ("src", "href"):
            if k in attrs:
                assert attrs[k].startswith(("data:", "#")), (tag, attrs[k][:60])
        assert tag not in ("script", "link", "iframe")
    assert "http://" not in html and "https://" not in html
    # every plot is embedded and identical to the PNG file beside the page
    imgs = [a["src"] for t, a in page.tags if t == "img"]
    assert len(imgs) == 3 and all(s.startswith("data:image/png;base64,") for s in imgs)
    embedded = {base64.b64decode(s.split(",", 1)[1]) for s in imgs}
    files = {(out / n).read_bytes() for n in PNG_FILES}
    assert embedded == files and all(b.startswith(b"\x89PNG\r\n\x1a\n") for b in files)
    # structure: verdict first, then the sections
    ids = [a.get("id") for _, a in page.tags if a.get("id")]
    assert ids[0] == "verdict"
    for sec in ("effort", "utilisation", "violations", "trajectories", "input-quality", "recheck"):
        assert sec in ids
    assert page.text[page.text.index("VIOLATIONS FOUND") + 1] == rec["verdict"]["summary"]
    # the tables carry the evidence's numbers
    body = " ".join(page.text)
    assert "panda_joint2" in body and "effort" in body
    assert "gap" in body and "0.599" in body and "0.700" in body
    # one pill per trajectory, in order (the words compared whole: "feasible" is in "infeasible")
    assert re.findall(r"<span class='pill (\w+)'>(\w+)</span>", html) == [
        ("ok", "feasible"), ("bad", "infeasible")]


def test_report_for_a_clean_bag_and_a_trajectory_only_bag(tmp_path):
    bag = make_bag(tmp_path / "bag", n=200)
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "o1")))
    html, page = parse(tmp_path / "o1" / "report.html")
    assert "FEASIBLE — no violations" in page.text
    assert "No live limit violations (effort, position, velocity, deceleration)." in page.text
    assert not (tmp_path / "o1" / "trajectories.png").exists()
    assert {a["alt"] for t, a in page.tags if t == "img"} == {
        "per-joint effort vs limit over time", "utilisation heat map, joint by time"}


def test_report_says_when_the_recheck_is_not_comparable(tmp_path):
    from dyn_node.core.robot.model import builtin_urdf

    bag = make_bag(tmp_path / "bag", n=200, outputs=True)
    urdf = tmp_path / "panda.urdf"
    urdf.write_text(builtin_urdf("panda"))
    run_audit(AuditOptions(bag=str(bag), robot_description=str(urdf), out=str(tmp_path / "o")))
    html, page = parse(tmp_path / "o" / "report.html")
    cells = [t for t in page.text if t.startswith("not comparable: joints: 7 recorded, 9 here")]
    assert len(cells) == 2  # gravity_torque and inverse_dynamics rows


def test_effort_plot_draws_the_measured_effort_signed():
    """Model torque −15 N·m and measured effort −15 N·m (they agree): the measured line is
    drawn below zero beside the model band, not at +15 as a |value| would put it."""
    import io

    import numpy as np
    from PIL import Image

    from dyn_node.audit.replay.common import SeriesBins
    from dyn_node.audit.report_plots import _ORANGE, effort_plot

    s = SeriesBins(1, 0, width_ns=10 * MS)
    for i in range(200):
        s.add(i * MS * 5, np.array([-15.0]), np.array([15 / 87]), np.array([87.0]), np.array([-15.0 - 0.01 * i]))
    assert s.meas_min[0, 0] < 0 and s.meas_max[0, 0] < 0
    img = np.asarray(Image.open(io.BytesIO(effort_plot(s, ["j"], 0, []))).convert("RGB")).astype(int)
    orange = np.array([int(_ORANGE[i:i + 2], 16) for i in (1, 3, 5)])
    ys, xs = np.nonzero(np.abs(img - orange).sum(axis=2) < 40)
    ys = ys[ys > 56]  # below the legend's sample line
    top, bottom = 62, 62 + 150 - 14  # the joint's panel; its y range is ±1.15·limit, 0 in the middle
    zero = (top + bottom) / 2
    assert len(ys) > 100
    assert ys.min() > zero  # all of it below zero
    # at −15 of ±100 N·m: 15 % of the half-height below the middle
    assert np.median(ys) == pytest.approx(zero + 15 / (1.15 * 87) * (bottom - top) / 2, abs=3)
