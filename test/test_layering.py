"""Only the ROS adapter imports rclpy: every other module of dyn_node imports with rclpy and every
ROS message package made unimportable.

Modules are found by walking the package, so a new module is covered without editing this test;
only the adapter allowlist below names modules.
"""
from __future__ import annotations

import ast
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


# ----------------------------------------------------------------------------------------------
# the house rules: no import circle, no folder over 20 modules, no module over 700 lines

MAX_MODULES_PER_FOLDER = 20
MAX_MODULE_LINES = 700


def _modules(root: Path, package: str) -> dict[str, Path]:
    """Every module of ``package`` under ``root`` by dotted name (a package by its ``__init__``)."""
    out = {}
    for path in sorted((root / package.replace(".", "/")).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement, at any depth (a function-level import counts), but not under
    ``if TYPE_CHECKING:`` (its ``else`` branch still counts)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def walk(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                walk(child)
            return
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        for child in ast.iter_child_nodes(node):
            walk(child)

    walk(tree)
    return found


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module → the modules of ``package`` it imports. Importing ``a.b.c`` runs the ``__init__``
    of ``a`` and ``a.b`` too, so those are edges as well (a registry whose package ``__init__``
    imports the registrants is a circle)."""
    mods = _modules(root, package)
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        edges: set[str] = set()
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    here = name.split(".") if is_pkg else name.split(".")[:-1]
                    here = here[:len(here) - (node.level - 1)]
                    base = ".".join(here + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                           for a in node.names]
            own = {".".join(name.split(".")[:k]) for k in range(1, name.count(".") + 1)}
            for target in targets:
                parts = target.split(".")
                # the packages on the way, but not the module's own (they run before it anyway);
                # its own package named as the target is an edge (it reaches that __init__)
                edges |= ({".".join(parts[:k]) for k in range(1, len(parts))} - own) & mods.keys()
                edges |= {target} & mods.keys()
        graph[name] = edges - {name}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def crowded_folders(root: Path, package: str, limit: int = MAX_MODULES_PER_FOLDER) -> dict[str, int]:
    """Folders of ``package`` holding more than ``limit`` modules (``__init__`` not counted)."""
    counts = {}
    for folder in [root / package, *(root / package).rglob("*")]:
        if folder.is_dir() and folder.name != "__pycache__":
            n = sum(1 for p in folder.glob("*.py") if p.name != "__init__.py")
            if n > limit:
                counts[str(folder.relative_to(root))] = n
    return counts


def long_modules(root: Path, package: str, limit: int = MAX_MODULE_LINES) -> dict[str, int]:
    """Modules of ``package`` over ``limit`` lines."""
    lines = {str(p.relative_to(root)): len(p.read_text().splitlines())
             for p in (root / package).rglob("*.py")}
    return {k: n for k, n in sorted(lines.items()) if n > limit}


def test_no_import_circle_between_dyn_node_modules():
    graph = import_graph(REPO, "dyn_node")
    # the walk sees the core's function-level imports (dynamics imports the rigid-body kernels
    # inside a method), so a circle through a lazy import cannot hide
    assert "dyn_node.core.compiled.rigid_kernels" in graph["dyn_node.core.robot.dynamics"]
    assert "dyn_node.core.check.joint_constraints" in graph["dyn_node.core.check.kinds"]
    assert circles(graph) == []


def test_no_import_circle_between_benchmark_modules():
    graph = import_graph(REPO, "benchmarks")
    # the subjects both halves of a pair share are modules of their own, imported by each
    assert "benchmarks.feasibility_subject" in graph["benchmarks.frames_bench"]
    assert "benchmarks.retime_panel" in graph["benchmarks.retime_start_bench"]
    assert circles(graph) == []


def test_no_folder_of_dyn_node_over_20_modules():
    assert crowded_folders(REPO, "dyn_node") == {}


def test_no_module_of_dyn_node_over_700_lines():
    assert long_modules(REPO, "dyn_node") == {}


def test_the_house_checks_fail_on_a_package_that_breaks_them(tmp_path):
    """The same checks on a small package: a circle through a function-level import, a registry
    reaching its registrants through its package ``__init__``, a relative-import circle; a
    ``TYPE_CHECKING`` import is no edge; 21 modules in a folder and a 701-line module are reported."""
    _package(tmp_path, {
        "house/__init__.py": "",
        "house/a.py": "def f():\n    from house import b\n",
        "house/b.py": "import house.a\n",
        "house/typed.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                           "    from house import a\nelse:\n    import math\n"),
        "house/a_user.py": "from house.typed import x\n",
        "house/reg/__init__.py": "from house.reg import kind_one\n",
        "house/reg/registry.py": "KINDS = []\n\ndef every():\n    from house import reg\n",
        "house/reg/kind_one.py": "from house.reg.registry import KINDS\n",
        "house/rel/__init__.py": "",
        "house/rel/x.py": "from . import y\n",
        "house/rel/y.py": "from .x import thing\n",
        "house/big/__init__.py": "",
        **{f"house/big/m{i:02d}.py": "" for i in range(21)},
        "house/ok/__init__.py": "",
        **{f"house/ok/m{i:02d}.py": "" for i in range(20)},
        "house/long.py": "x = 1\n" * 701,
        "house/fits.py": "x = 1\n" * 700,
    })
    graph = import_graph(tmp_path, "house")
    assert graph["house.typed"] == set()
    assert circles(graph) == [["house.a", "house.b"], ["house.reg", "house.reg.kind_one", "house.reg.registry"],
                              ["house.rel.x", "house.rel.y"]]
    assert crowded_folders(tmp_path, "house") == {"house/big": 21}
    assert long_modules(tmp_path, "house") == {"house/long.py": 701}
