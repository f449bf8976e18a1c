"""Static scene objects and MuJoCo's contact-solver settings for dyn_sim (no rclpy).

A scene file (YAML) lists the static objects the robot can touch::

    collide_links: [panda_hand, panda_leftfinger]   # optional; default: every link with geometry
    objects:
      - name: table
        type: box            # box | plane | sphere
        size: [0.6, 0.8, 0.04]   # box: FULL edge lengths x y z (m), as URDF <box size>;
                                 # sphere: [radius]; plane: [x, y] full extents, [0, 0] infinite
        position: [0.5, 0.0, 0.2]        # m, robot base frame (the URDF root link = MuJoCo world)
        orientation: [0, 0, 0, 1]        # quaternion x y z w, base frame (normalised on load)
        friction: 0.8                    # sliding coefficient, or [sliding, torsional, rolling]

Every key is checked when the file is loaded: unknown keys, missing ones, NaN/Inf, non-positive
sizes, negative friction, duplicate names and unknown ``collide_links`` are refused with a
:class:`SceneError` naming the object and key. How the objects enter the MuJoCo model (collision
filtering, friction and solref/solimp precedence): docs/SIMULATOR.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import mujoco
import numpy as np
from dyn_node.errors import STATE_ERROR, DynNodeError
from dyn_node.io.files import FileProblem, read_text
from dyn_node.io.safe_load import LoadError, load_yaml

OBJECT_TYPES = ("box", "plane", "sphere")
_OBJECT_KEYS = {"name", "type", "size", "position", "orientation", "friction"}
_SCENE_KEYS = {"objects", "collide_links"}
_SIZE_LEN = {"box": 3, "sphere": 1, "plane": 2}
#: A scene file is a few objects: larger is not a scene (read at most this many bytes).
MAX_SCENE_BYTES = 1024 * 1024
INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
               "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
               "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG,
           "pgs": mujoco.mjtSolver.mjSOL_PGS}
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


class SceneError(DynNodeError):
    """A scene file or solver setting that cannot be used (refused at start)."""

    failure_label = STATE_ERROR


@dataclass(frozen=True)
class SceneObject:
    """One static object. ``size`` as in the file (box: full extents), ``quat_xyzw`` unit."""

    name: str
    type: str
    size: tuple[float, ...]
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    friction: tuple[float, float, float]

    @property
    def mujoco_size(self) -> list[float]:
        """MuJoCo's geom size: half extents for a box and a plane (0 = infinite plane)."""
        if self.type == "sphere":
            return [self.size[0], 0.0, 0.0]
        if self.type == "box":
            return [0.5 * s for s in self.size]
        return [0.5 * self.size[0], 0.5 * self.size[1], 1.0]  # third: grid spacing (display)


@dataclass(frozen=True)
class Scene:
    """Objects plus the robot links allowed to touch them (empty: every link with geometry)."""

    objects: tuple[SceneObject, ...] = ()
    collide_links: tuple[str, ...] = ()
    source: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)


@dataclass(frozen=True)
class SolverSettings:
    """MuJoCo solver settings used with a scene; the defaults are MuJoCo's own except
    ``integrator`` (MuJoCo: euler) and ``noslip_iterations`` (MuJoCo: 0). RK4: Euler at 1 ms
    drifts 12% of the peak kinetic energy in the free-motion check, RK4 1e-5, for ~25% more
    time per step. No-slip: without it soft contacts creep under a tangential load (a held
    press on the table lost 30% of its normal force in 5 s).

    ``solref`` = (time constant s, damping ratio) and ``solimp`` = (d0, d_width, width m,
    midpoint, power) apply to every robot–scene contact.
    """

    integrator: str = "rk4"
    solver: str = "newton"
    iterations: int = 100
    tolerance: float = 1e-8
    cone: str = "pyramidal"
    solref: tuple[float, float] = (0.02, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    noslip_iterations: int = 20

    def __post_init__(self) -> None:
        for key, table in (("integrator", INTEGRATORS), ("solver", SOLVERS), ("cone", CONES)):
            if getattr(self, key) not in table:
                raise SceneError(f"{key} '{getattr(self, key)}' unknown (one of {', '.join(table)})",
                                 code=f"bad_{key}")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise SceneError(f"iterations must be an integer ≥ 1, got {self.iterations}",
                             code="bad_iterations")
        if not (isinstance(self.noslip_iterations, int) and self.noslip_iterations >= 0):
            raise SceneError(f"noslip_iterations must be an integer ≥ 0, got {self.noslip_iterations}",
                             code="bad_iterations")
        if not (self.tolerance >= 0 and math.isfinite(self.tolerance)):
            raise SceneError(f"tolerance must be finite and ≥ 0, got {self.tolerance}", code="bad_tolerance")
        ref, imp = tuple(self.solref), tuple(self.solimp)
        if len(ref) != 2 or not all(math.isfinite(x) and x > 0 for x in ref):
            raise SceneError(f"solref needs 2 positive values (time constant s, damping ratio), got {list(ref)}",
                             code="bad_solref")
        if (len(imp) != 5 or not all(math.isfinite(x) for x in imp) or not 0 < imp[0] < 1
                or not 0 < imp[1] < 1 or imp[2] <= 0 or not 0 < imp[3] < 1 or imp[4] < 1):
            raise SceneError("solimp needs (d0, d_width in (0, 1), width > 0, midpoint in (0, 1), "
                             f"power ≥ 1), got {list(imp)}", code="bad_solimp")

    def apply(self, mj: mujoco.MjModel) -> None:
        """Write the global options into a compiled model (geom solref/solimp: :func:`add_scene`)."""
        mj.opt.integrator = int(INTEGRATORS[self.integrator])
        mj.opt.solver = int(SOLVERS[self.solver])
        mj.opt.iterations = int(self.iterations)
        mj.opt.tolerance = float(self.tolerance)
        mj.opt.cone = int(CONES[self.cone])
        mj.opt.noslip_iterations = int(self.noslip_iterations)

    def to_dict(self) -> dict[str, Any]:
        return {"integrator": self.integrator, "solver": self.solver, "iterations": self.iterations,
                "tolerance": self.tolerance, "cone": self.cone, "solref": list(self.solref),
                "solimp": list(self.solimp),
                "noslip_iterations": self.noslip_iterations}


def _numbers(where: str, key: str, value: Any, n: int | None) -> tuple[float, ...]:
    vals = value if isinstance(value, (list, tuple)) else [value]
    try:
        out = tuple(float(v) for v in vals if not isinstance(v, bool))
    except (TypeError, ValueError):
        raise SceneError(f"{where}: '{key}' must be numbers, got {_short(value)}", code="bad_value") from None
    except OverflowError:  # an integer beyond float range
        raise SceneError(f"{where}: '{key}' has a number beyond float range", code="non_finite") from None
    if len(out) != len(vals) or (n is not None and len(out) != n):
        raise SceneError(f"{where}: '{key}' needs {n} numbers, got {_short(value)}", code="bad_value")
    if not all(math.isfinite(v) for v in out):
        raise SceneError(f"{where}: '{key}' is not finite ({list(out)})", code="non_finite")
    return out


def _short(value: Any) -> str:
    """A value for a one-line message: at most 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _object(i: int, raw: Any) -> SceneObject:
    where = f"objects[{i}]"
    if not isinstance(raw, Mapping):
        raise SceneError(f"{where} must be a mapping, got {type(raw).__name__}", code="bad_object")
    unknown = set(raw) - _OBJECT_KEYS
    missing = {"name", "type", "size", "position"} - set(raw)
    if unknown or missing:
        raise SceneError(f"{where}: unknown keys {sorted(unknown)}, missing keys {sorted(missing)} "
                         f"(allowed: {sorted(_OBJECT_KEYS)})", code="bad_keys")
    name, kind = raw["name"], raw["type"]
    if not isinstance(name, str) or not name.strip():
        raise SceneError(f"{where}: 'name' must be a non-empty string", code="bad_name")
    where = f"object '{name}'"
    if kind not in OBJECT_TYPES:
        raise SceneError(f"{where}: type '{kind}' unknown (one of {', '.join(OBJECT_TYPES)})",
                         code="bad_type")
    size = _numbers(where, "size", raw["size"], _SIZE_LEN[kind])
    if kind == "plane" and size != (0.0, 0.0) and not all(s > 0 for s in size):
        raise SceneError(f"{where}: plane size must be positive full extents or [0, 0] (infinite), "
                         f"got {list(size)}", code="bad_size")
    if kind != "plane" and not all(s > 0 for s in size):
        raise SceneError(f"{where}: size must be positive, got {list(size)}", code="bad_size")
    pos = _numbers(where, "position", raw["position"], 3)
    quat = np.array(_numbers(where, "orientation", raw.get("orientation", [0, 0, 0, 1]), 4))
    with np.errstate(over="ignore"):
        norm = float(np.sqrt(np.sum(quat * quat)))
    if not math.isfinite(norm):
        raise SceneError(f"{where}: orientation {list(quat)} cannot be normalised (its norm overflows)",
                         code="bad_orientation")
    if norm < 1e-6:
        raise SceneError(f"{where}: orientation is a zero quaternion", code="bad_orientation")
    fr = _numbers(where, "friction", raw.get("friction", 1.0), None)
    if not 1 <= len(fr) <= 3 or any(f < 0 for f in fr):
        raise SceneError(f"{where}: friction needs 1 to 3 values ≥ 0, got {list(fr)}", code="bad_friction")
    friction = fr + (0.005, 0.0001)[len(fr) - 1:]  # MuJoCo's default torsional and rolling
    return SceneObject(name=name, type=kind, size=size, position=pos,
                       quat_xyzw=tuple(float(x) for x in quat / norm), friction=friction)


def parse_scene(raw: Any, *, link_names: Iterable[str], source: str = "") -> Scene:
    """Validate a scene document (the YAML's content) against the robot's link names."""
    if not isinstance(raw, Mapping):
        raise SceneError(f"scene {source}: top level must be a mapping with 'objects'", code="bad_scene")
    unknown = set(raw) - _SCENE_KEYS
    if unknown or "objects" not in raw:
        raise SceneError(f"scene {source}: unknown keys {sorted(unknown)}"
                         f"{'' if 'objects' in raw else ', missing objects'} (allowed: {sorted(_SCENE_KEYS)})",
                         code="bad_keys")
    if not isinstance(raw["objects"], list):
        raise SceneError(f"scene {source}: 'objects' must be a list", code="bad_scene")
    objects = tuple(_object(i, o) for i, o in enumerate(raw["objects"]))
    names = [o.name for o in objects]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SceneError(f"scene {source}: duplicate object names {dup}", code="duplicate_name")
    links = set(link_names)
    collide = raw.get("collide_links") or []
    if not isinstance(collide, list) or not all(isinstance(x, str) for x in collide):
        raise SceneError(f"scene {source}: 'collide_links' must be a list of link names", code="bad_links")
    bad = sorted(set(collide) - links)
    if bad:
        raise SceneError(f"scene {source}: collide_links {bad} are not links of the robot "
                         f"(links: {', '.join(sorted(links))})", code="unknown_link")
    clash = sorted(set(names) & links)
    if clash:
        raise SceneError(f"scene {source}: object names {clash} are robot link names", code="bad_name")
    return Scene(objects=objects, collide_links=tuple(collide), source=source)


def load_scene(path: str | Path, *, link_names: Iterable[str]) -> Scene:
    """Read and validate a scene file with the project's bounded, strict reader (a regular file
    of at most :data:`MAX_SCENE_BYTES`, UTF-8, YAML without duplicate keys, deep nesting or alias
    bombs); SceneError (code ``unreadable``) when it cannot be read."""
    p = Path(path)
    try:
        raw = load_yaml(read_text(p, max_bytes=MAX_SCENE_BYTES))
    except (FileProblem, LoadError) as exc:
        raise SceneError(f"scene file {p} cannot be read: {exc}", code="unreadable") from None
    return parse_scene(raw, link_names=link_names, source=str(p))


#: contype/conaffinity: robot geoms collide with scene geoms only, never with each other.
ROBOT_CONTYPE, ROBOT_CONAFFINITY = 1, 0
SCENE_CONTYPE, SCENE_CONAFFINITY = 0, 1
_GEOM_TYPES = {"box": mujoco.mjtGeom.mjGEOM_BOX, "plane": mujoco.mjtGeom.mjGEOM_PLANE,
               "sphere": mujoco.mjtGeom.mjGEOM_SPHERE}


def add_scene(spec: mujoco.MjSpec, scene: Scene, solver: SolverSettings) -> None:
    """Add ``scene``'s objects to the world of an uncompiled robot spec and filter collisions.

    Robot geoms (all geoms already in ``spec``) get contype 1 / conaffinity 0 and scene geoms
    0 / 1, so only robot–scene pairs are tested (self-collisions never). Links outside
    ``collide_links`` (when given) collide with nothing. Scene geoms have priority 1, so their
    friction, solref and solimp decide every robot–scene contact.
    """
    allowed = set(scene.collide_links)
    for g in spec.geoms:
        link = g.parent.name
        on = not allowed or link in allowed
        g.contype = ROBOT_CONTYPE if on else 0
        g.conaffinity = ROBOT_CONAFFINITY
    for o in scene.objects:
        x, y, z, w = o.quat_xyzw
        spec.worldbody.add_geom(
            name=o.name, type=_GEOM_TYPES[o.type], size=o.mujoco_size, pos=list(o.position),
            quat=[w, x, y, z], friction=list(o.friction), contype=SCENE_CONTYPE,
            conaffinity=SCENE_CONAFFINITY, priority=1, condim=3,
            solref=list(solver.solref), solimp=list(solver.solimp))
