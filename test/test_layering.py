"""Only the ROS adapter imports rclpy: every other module of dyn_node imports with rclpy and every
ROS message package made unimportable.

Modules are found by walking the package, so a new module is covered without editing this test;
only the adapter allowlist below names modules.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# The ROS side, allowed to import rclpy and the message packages (a package entry covers its
# submodules): the ros subpackage (the two nodes, message conversion, parameters, the recording
# bridge, process entry, the client library, the demo) and dyn_node.client, which re-exports the
# client library at the name DESIGN.md gives it.
ADAPTER = ("ros", "client")

# Run in a fresh interpreter: a meta-path finder refusing the ROS client and message packages is
# installed before anything of the package is imported; each module not in the allowlist is then
# imported (packages recursed into with pkgutil) and the outcome printed as JSON.
CHECKER = r'''
import importlib, importlib.abc, json, pkgutil, sys, traceback

PACKAGE, ALLOWED = sys.argv[1], set(json.loads(sys.argv[2]))
ROS_TOPS = {"rclpy", "rcl_interfaces", "builtin_interfaces", "rosgraph_msgs"}

def is_ros(name):
    top = name.partition(".")[0]
    return (top in ROS_TOPS or top.startswith("rosidl_")
            or top.endswith(("_msgs", "_srvs", "_interfaces")))

class RefuseRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if is_ros(name):
            raise ModuleNotFoundError(f"No module named {name!r} (refused: ROS side)", name=name)
        return None

assert not [m for m in sys.modules if is_ros(m)], "a ROS module was imported before the block"
sys.meta_path.insert(0, RefuseRos())

def allowed(name):
    rel = name[len(PACKAGE) + 1:]
    return any(rel == a or rel.startswith(a + ".") for a in ALLOWED)

imported, failed, skipped = [], {}, []

def visit(path, prefix):
    for info in pkgutil.iter_modules(path, prefix):
        if allowed(info.name):
            skipped.append(info.name)
            continue
        try:
            mod = importlib.import_module(info.name)
        except BaseException as e:  # SystemExit or anything: the module did not import
            failed[info.name] = "".join(traceback.format_exception_only(type(e), e)).strip()
            continue
        imported.append(info.name)
        if info.ispkg:
            visit(mod.__path__, info.name + ".")

root = importlib.import_module(PACKAGE)
visit(root.__path__, PACKAGE + ".")
print(json.dumps({"imported": imported, "failed": failed, "skipped": skipped,
                  "ros_loaded": sorted(m for m in sys.modules if is_ros(m))}))
'''


def run_checker(package: str, allowed: tuple[str, ...], *, path: Path = REPO) -> dict:
    """The checker's outcome for ``package`` found under ``path`` (``-c`` puts the cwd first on sys.path)."""
    r = subprocess.run([sys.executable, "-c", CHECKER, package, json.dumps(list(allowed))],
                       capture_output=True, text=True, timeout=240, cwd=str(path))
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_everything_but_the_ros_adapter_imports_without_rclpy():
    out = run_checker("dyn_node", ADAPTER)
    assert out["failed"] == {}, "\n".join(f"{k}: {v}" for k, v in out["failed"].items())
    assert out["ros_loaded"] == []
    # the walk found the core (not an empty package), and every allowlist entry names a module
    # that exists, so a renamed adapter module cannot leave a stale entry behind
    assert {"dyn_node.core.check.feasibility", "dyn_node.core.live.monitor", "dyn_node.audit.bag_audit",
            "dyn_node.sim.simulator", "dyn_node.bag.reader"} <= set(out["imported"])
    assert sorted(n.removeprefix("dyn_node.") for n in out["skipped"]) == sorted(ADAPTER)


def _package(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def test_the_check_fails_when_a_core_module_imports_rclpy(tmp_path):
    """The same checker on a small package: a core module importing rclpy (directly, through a
    message package, or in a subpackage) is reported; the allowlisted adapter is not imported."""
    _package(tmp_path, {
        "layer_pkg/__init__.py": "",
        "layer_pkg/core.py": "import math\n",
        "layer_pkg/leaky.py": "import rclpy\n",
        "layer_pkg/msgs_user.py": "from sensor_msgs.msg import JointState\n",
        "layer_pkg/sub/__init__.py": "",
        "layer_pkg/sub/deep.py": "from rclpy.node import Node\n",
        "layer_pkg/adapter.py": "import rclpy\n",
    })
    out = run_checker("layer_pkg", ("adapter",), path=tmp_path)
    assert sorted(out["failed"]) == ["layer_pkg.leaky", "layer_pkg.msgs_user", "layer_pkg.sub.deep"]
    assert "'rclpy'" in out["failed"]["layer_pkg.leaky"]
    assert "'sensor_msgs'" in out["failed"]["layer_pkg.msgs_user"]
    assert sorted(out["imported"]) == ["layer_pkg.core", "layer_pkg.sub"]
    assert out["skipped"] == ["layer_pkg.adapter"] and out["ros_loaded"] == []
