"""dyn-fleet leaves nothing behind but its --out: no Ray session folder in the temporary
directory, no Ray process alive once the command has returned (also after Ctrl-C); and every
input gets a row, a directory named like a bag file too."""
from __future__ import annotations

import os
import selectors
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet_bags import BagSpec, write_bag  # noqa: E402

from dyn_node.fleet import engine as fleet  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    for k in range(4):  # long enough that bags are still being audited when Ctrl-C comes
        write_bag(root, BagSpec(f"c{k}", "panda", 20.0, trajectories=(False,), start_s=k))
    return root


@pytest.fixture
def short_tmp():
    """A short TMPDIR of the test's own (Ray's socket paths under it must stay < 108 bytes)."""
    d = Path(tempfile.mkdtemp(prefix="i27", dir="/tmp"))
    yield d
    import shutil

    shutil.rmtree(d, ignore_errors=True)


def _session_procs(sid: int) -> list[str]:
    """Live (non-zombie) processes of session ``sid``: the command and everything it started."""
    out = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")[:120].decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append(f"{pid}: {cmd}")
    return out


def _start(bags: Path, out: Path, tmp: Path) -> subprocess.Popen:
    env = dict(os.environ, TMPDIR=str(tmp), PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-m", "dyn_node.fleet.engine", str(bags), "--out", str(out),
                             "--workers", "2"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, cwd=str(tmp))


def test_a_run_leaves_no_ray_session_folder(bags, short_tmp, tmp_path):
    p = _start(bags, tmp_path / "out", short_tmp)
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    assert out.startswith("FEASIBLE: 4 bags: 4 ok")
    assert list(short_tmp.iterdir()) == []          # no ray/session_* (nor our own folder)
    assert _session_procs(p.pid) == []


def test_ctrl_c_ends_rays_processes_and_removes_its_folder(bags, short_tmp, tmp_path):
    p = _start(bags, tmp_path / "out", short_tmp)
    sel = selectors.DefaultSelector()
    sel.register(p.stderr, selectors.EVENT_READ)
    started = False
    while not started and sel.select(timeout=120):  # the progress line: Ray is up, bags in flight
        line = p.stderr.readline()
        if not line:
            break
        started = line.startswith("dyn-fleet [")
    assert started, "dyn-fleet never started its bags"
    os.killpg(p.pid, signal.SIGINT)  # as Ctrl-C does: the whole foreground process group
    _out, err = p.communicate(timeout=120)
    assert p.returncode == 130 and "dyn-fleet: interrupted" in err and "Traceback" not in err, err[-2000:]
    # the moment the command has returned, nothing it started is left, and nothing in TMPDIR
    assert _session_procs(p.pid) == []
    assert list(short_tmp.iterdir()) == []


def test_a_directory_named_like_a_bag_file_gets_a_row(tmp_path):
    (tmp_path / "site" / "x.mcap").mkdir(parents=True)
    (tmp_path / "site" / "y.mcap").mkdir()
    (tmp_path / "site" / "y.mcap" / "notes.txt").write_text("not a bag")
    found = fleet.discover([str(tmp_path)])
    assert found == [(tmp_path / "site" / "x.mcap").resolve(), (tmp_path / "site" / "y.mcap").resolve()]
    assert fleet.discover([str(tmp_path / "site" / "x.mcap")]) == [(tmp_path / "site" / "x.mcap").resolve()]
    for b in found:
        job = fleet.BagJob(str(b), fleet.bag_id(b), str(tmp_path / "out"), fleet.FleetConfig(), "h")
        row = fleet.audit_bag(job).row
        assert (row["exit_category"], row["error_code"], row["path"]) == ("unusable", "bag_empty", str(b))
        assert "holds no .mcap file" in row["error"]
