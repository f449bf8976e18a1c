"""package.xml and the README's colcon pip line against what ``dyn_node/`` imports: every ROS
package the code imports (message, service and action packages, rclpy and friends) is a
<depend>/<exec_depend> of package.xml, and every other third-party import is either a rosdep
key there or pinned on the README's colcon ``pip install`` line (issue 27: geometry_msgs was
missing, and ray, pyarrow and duckdb were not on the pip line). The import list is derived from
the code, so a new import fails here until it is declared."""
from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET

from conftest import REPO

# ROS packages imported without a .msg/.srv/.action submodule
ROS_LIBRARIES = {"rclpy", "rcl_interfaces", "ament_index_python", "builtin_interfaces"}
# Third-party Python imports: the rosdep key package.xml declares, or None when rosdep has no
# key and the README's colcon pip line installs it (pip name). Unknown imports fail the test.
PYTHON_DEPS = {
    "numpy": ("python3-numpy", None), "numba": ("python3-numba", None),
    "yaml": ("python3-yaml", None), "matplotlib": ("python3-matplotlib", None),
    "jsonschema": ("python3-jsonschema", None), "PIL": ("python3-pil", None),
    "pinocchio": ("pinocchio", None), "example_robot_data": ("example-robot-data", None),
    "mcap": (None, "mcap"), "mcap_ros2": (None, "mcap-ros2-support"), "mujoco": (None, "mujoco"),
    "ray": (None, "ray"), "pyarrow": (None, "pyarrow"), "zstandard": (None, "zstandard"),
    "lz4": (None, "lz4"), "toppra": (None, "toppra"), "rosbags": (None, "rosbags"),
}
# Used in the README's own commands rather than imported by dyn_node (the DuckDB one-liner)
README_TOOLS = {"duckdb"}


def _imports() -> dict[str, set[str]]:
    """Top-level module -> the submodules imported from it (``msg``, ``srv`` ...), over every
    module of dyn_node/ (absolute imports only; ours and the standard library left out)."""
    found: dict[str, set[str]] = {}
    for path in (REPO / "dyn_node").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0
                     and node.module else [])
            for name in names:
                top, _, rest = name.partition(".")
                if top != "dyn_node" and top not in sys.stdlib_module_names:
                    found.setdefault(top, set()).add(rest.split(".")[0])
    return found


def _package_xml_deps() -> set[str]:
    root = ET.parse(REPO / "package.xml").getroot()
    return {e.text.strip() for tag in ("depend", "exec_depend") for e in root.iter(tag)}


def _colcon_pip_line() -> dict[str, str]:
    """name -> version of the README's colcon section's ``pip install`` command."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Building in a colcon workspace", 1)[1].split("\n## ", 1)[0]
    command = re.search(r"^pip install (.*?)(?<!\\)$", section, re.M | re.S)
    assert command, "no pip install line in the colcon section"
    return dict(re.findall(r"([A-Za-z0-9_.-]+)==([^\s\\]+)", command.group(1)))


def _pins() -> dict[str, str]:
    text = (REPO / "requirements.txt").read_text(encoding="utf-8")
    return {m.group(1).lower(): m.group(2) for m in re.finditer(r"^([A-Za-z0-9_.-]+)==(\S+)", text, re.M)}


def test_every_ros_import_is_a_package_xml_dependency():
    deps = _package_xml_deps()
    ros = {top for top, subs in _imports().items() if subs & {"msg", "srv", "action"}}
    ros |= ROS_LIBRARIES & set(_imports())
    assert "geometry_msgs" in ros  # node.py's WrenchStamped: the list is really derived
    assert sorted(ros - deps) == []


def test_every_python_import_is_declared_or_on_the_pip_line():
    deps, pip, pins = _package_xml_deps(), _colcon_pip_line(), _pins()
    ros = {top for top, subs in _imports().items() if subs & {"msg", "srv", "action"}}
    python = set(_imports()) - ros - ROS_LIBRARIES
    assert sorted(python - set(PYTHON_DEPS)) == [], "a new import: add it to PYTHON_DEPS"
    for module in sorted(python):
        key, pip_name = PYTHON_DEPS[module]
        if key is not None:
            assert key in deps, f"{module}: package.xml lacks {key}"
        else:  # on the pip line, at the version requirements.txt pins
            assert pip.get(pip_name) == pins[pip_name.lower()], (module, pip_name, pip)
    for tool in README_TOOLS:
        assert pip.get(tool) == pins[tool], tool
