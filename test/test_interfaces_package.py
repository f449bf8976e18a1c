"""The interface packages under interfaces/: sources only in git, the types built and importable."""

from __future__ import annotations

import re
import shutil
import subprocess
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
