"""The interface packages under interfaces/: sources only in git, the types built and importable."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what an interface package's sources are; anything else under interfaces/ is a build output
SOURCE = re.compile(r"(package\.xml|CMakeLists\.txt|README\.md|build\.sh|.*\.(msg|srv|action|cmake))")
# what a build of an interface package leaves behind (rosidl, cmake, colcon)
BUILT = re.compile(
    r"(^|/)(build|install|log|CMakeFiles|rosidl_generator_\w+|rosidl_typesupport_\w+)/"
    r"|\.(so|o|a|pyc|idl)$|(^|/)CMakeCache\.txt$|(^|/)_\w+_s\.c$|__type_support\.cpp$")


def _tracked() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True)
    return out.stdout.splitlines()


def test_no_built_files_are_committed() -> None:
    tracked = _tracked()
    assert any(p.startswith("interfaces/dyn_node_interfaces/") for p in tracked), \
        "git ls-files lists no interface sources: the test would pass vacuously"
    built = [p for p in tracked if BUILT.search(p)]
    assert built == [], f"build outputs committed: {built[:10]}"
    odd = [p for p in tracked if p.startswith("interfaces/") and not SOURCE.fullmatch(p.rsplit("/", 1)[-1])]
    assert odd == [], f"files under interfaces/ that are not interface sources: {odd}"


def test_the_patterns_catch_what_a_build_leaves() -> None:
    # the two patterns above, against names a real build writes (so the first test can fail)
    for p in ("build/interfaces/dyn_node_interfaces/CMakeCache.txt",
              "interfaces/dyn_node_interfaces/rosidl_generator_py/dyn_node_interfaces/srv/x.py",
              "lib/libdyn_node_interfaces__rosidl_typesupport_c.so",
              "interfaces/dyn_node_interfaces/srv/CheckTrajectory.idl"):
        assert BUILT.search(p), p
    for p in ("interfaces/dyn_node_interfaces/srv/CheckTrajectory.srv",
              "interfaces/cmake/venv_wheels.cmake", "interfaces/build.sh"):
        assert not BUILT.search(p) and SOURCE.fullmatch(p.rsplit("/", 1)[-1]), p


def test_generated_types_match_the_sources() -> None:
    srv = pytest.importorskip("dyn_node_interfaces.srv",
                              reason="dyn_node_interfaces not built (make builds it into .venv)")
    msg = pytest.importorskip("dyn_node_interfaces.msg")
    source = (ROOT / "interfaces/dyn_node_interfaces/srv/CheckTrajectory.srv").read_text()
    response_fields = [ln.split()[1] for ln in source.split("---")[1].splitlines()
                       if ln.strip() and not ln.startswith("#")]
    assert list(srv.CheckTrajectory.Response.get_fields_and_field_types()) == response_fields
    assert list(msg.Contact.get_fields_and_field_types()) == [
        "body1", "body2", "position", "normal", "force", "penetration_depth"]
    assert msg.ContactTruth.get_fields_and_field_types() == {
        "header": "std_msgs/Header", "contacts": "sequence<dyn_node_interfaces/Contact>",
        "link_names": "sequence<string>", "link_wrenches": "sequence<geometry_msgs/Wrench>"}


def _package(root: Path, name: str, depends: tuple[str, ...] = ()) -> Path:
    d = root / name
    d.mkdir()
    deps = "".join(f"<depend>{x}</depend>" for x in depends)
    (d / "package.xml").write_text(f'<?xml version="1.0"?><package format="3"><name>{name}</name>'
                                   f"<version>0.0.0</version>{deps}</package>")
    (d / "CMakeLists.txt").write_text(f"cmake_minimum_required(VERSION 3.20)\nproject({name} NONE)\n")
    return d


def test_build_script_orders_by_dependency_and_skips_a_foreign_control_msgs(tmp_path) -> None:
    """interfaces/build.sh on stand-in packages (empty CMake projects): a package after the one it
    depends on whatever order they are given in; a control_msgs the venv already imports and did
    not get from this script is left alone; the ones it builds are marked as its own."""
    if shutil.which("cmake") is None:
        pytest.skip("cmake is not installed")
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)
    pkgs = tmp_path / "src"
    pkgs.mkdir()
    a = _package(pkgs, "alpha_msgs", ("zeta_msgs",))
    z = _package(pkgs, "zeta_msgs")
    c = _package(pkgs, "control_msgs")
    foreign = tmp_path / "site"
    (foreign / "control_msgs" / "msg").mkdir(parents=True)
    (foreign / "control_msgs" / "__init__.py").write_text("")
    (foreign / "control_msgs" / "msg" / "__init__.py").write_text("")
    env = dict(os.environ, PYTHONPATH=str(foreign))
    run = subprocess.run([str(ROOT / "interfaces" / "build.sh"), "--venv", str(venv), "--build-dir",
                          str(tmp_path / "build"), str(a), str(c), str(z)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("build.sh: ")]
    built = [ln.split()[2] for ln in lines if ln.startswith("build.sh: building ")]
    assert built == ["zeta_msgs", "alpha_msgs"], lines
    assert any(ln.startswith("build.sh: skipping control_msgs: the venv already has") for ln in lines), lines
    assert (venv / "share" / "zeta_msgs" / "dyn_node_built").read_text().strip() == str(z.resolve())
    # without a foreign one, control_msgs is built like the others
    run = subprocess.run([str(ROOT / "interfaces" / "build.sh"), "--venv", str(venv), "--build-dir",
                          str(tmp_path / "build"), str(c)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert run.returncode == 0 and "build.sh: building control_msgs" in run.stdout, run.stdout + run.stderr


def test_make_rebuilds_the_interfaces_when_a_file_changes_and_test_needs_them() -> None:
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    srv = "interfaces/dyn_node_interfaces/srv/CheckTrajectory.srv"
    out = subprocess.run(["make", "-n", "-o", ".venv/.dyn_node-installed", "-o", ".venv/.dyn_node-kernels",
                          "-W", srv, "test"], cwd=ROOT, capture_output=True, text=True, timeout=60).stdout
    build = out.find("interfaces/build.sh --venv .venv")
    assert build >= 0 and "interfaces/dyn_node_interfaces" in out[build:].splitlines()[0], out
    assert out.find("-m pytest") > build, out   # built before the tests run
