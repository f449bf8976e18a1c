"""Task-space limits from the limits YAML: ``frame_limits``, ``robot_limits``, ``task_wrench``,
``base_limits`` and ``grasp``, beside ``joint_limits`` (also under ``<node>: ros__parameters:``).

Parsed into frozen dataclasses (SI units; vectors in the named frame's axes, base quantities in
the URDF root frame). Every error is a :class:`ModelError` naming the file, section, key and
frame; unknown keys (top-level too) suggest the intended one. A missing limit is ``inf``. MoveIt's
``default_velocity_scaling_factor`` / ``default_acceleration_scaling_factor`` are accepted at the
top level and unused (planning defaults, not limits).
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np

from dyn_node.errors import ModelError
from dyn_node.io.text import escape, name_list, shown

if TYPE_CHECKING:
    from dyn_node.core.check.force_laws import SupportPolygon

JOINT_LIMITS_KEY = "joint_limits"
TASK_SECTIONS = ("frame_limits", "robot_limits", "task_wrench", "base_limits", "grasp")
#: Accepted at the top level because MoveIt's joint_limits.yaml carries them; not used.
UNUSED_TOP_LEVEL_KEYS = frozenset({"default_velocity_scaling_factor",
                                   "default_acceleration_scaling_factor"})
#: Every key a limits file may have at its top level (or beside joint_limits in ros__parameters).
LIMITS_FILE_KEYS = frozenset({JOINT_LIMITS_KEY, *TASK_SECTIONS, *UNUSED_TOP_LEVEL_KEYS})

FRAME_LIMIT_KEYS = ("point", "max_linear_speed", "max_angular_speed", "max_linear_acceleration",
                    "max_transferred_energy")
ROBOT_LIMIT_KEYS = ("max_kinetic_energy",)
TASK_WRENCH_KEYS = ("frame", "force", "torque")
BASE_LIMIT_KEYS = ("max_force", "max_moment", "base_mass", "base_com", "support_polygon")
GRASP_KEYS = ("frame", "normal_axis", "friction_coefficient", "grip_force", "faces")

#: Horizontal share of |g| above which gravity is not "along −z" for tipping.
VERTICAL_GRAVITY_TOLERANCE = 1e-9
#: Largest base_mass (kg): its weight and moments stay far from overflow.
MAX_BASE_MASS_KG = 1e9


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest candidate, or ``""``: for unknown-key errors."""
    close = difflib.get_close_matches(str(name)[:200], sorted(candidates), n=1)
    return f" (did you mean '{escape(close[0])}'?)" if close else ""


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class FrameLimits:
    """Limits at ``point`` (m, in ``frame``'s axes) of one link; ``inf``: not limited."""

    frame: str
    point: np.ndarray
    max_linear_speed: float = math.inf          # m/s
    max_angular_speed: float = math.inf         # rad/s
    max_linear_acceleration: float = math.inf   # m/s², classical, gravity excluded
    max_transferred_energy: float = math.inf    # J, ½·m_u·v² (advisory)


@dataclass(frozen=True)
class RobotLimits:
    max_kinetic_energy: float = math.inf        # J, ½ q̇ᵀM(q)q̇


@dataclass(frozen=True)
class TaskWrench:
    """What the tool exerts on the environment at ``frame``'s origin, in its axes."""

    frame: str
    force: np.ndarray     # N
    torque: np.ndarray    # N·m


@dataclass(frozen=True)
class BaseLimits:
    """Mounting load at the root origin (root axes) and, with ``support_polygon``, tipping."""

    max_force: float = math.inf                 # N
    max_moment: float = math.inf                # N·m
    base_mass: float = 0.0                      # kg
    base_com: np.ndarray | None = None          # m, root frame
    support_polygon: SupportPolygon | None = None   # root z = 0 plane, counter-clockwise


@dataclass(frozen=True)
class GraspLimits:
    """The grip holding the payload (``payload.*``) at ``frame``; ``normal_axis`` is a unit
    vector in its axes."""

    frame: str
    normal_axis: np.ndarray
    friction_coefficient: float
    grip_force: float       # N per face
    faces: int

    @property
    def max_tangential_force(self) -> float:
        """μ·grip_force·faces (N): the friction cone's radius."""
        return self.friction_coefficient * self.grip_force * self.faces


@dataclass(frozen=True)
class TaskLimits:
    """Everything the limits file configures beyond ``joint_limits``; ``None``: section absent."""

    source: str
    frame_limits: tuple[FrameLimits, ...] = ()
    robot_limits: RobotLimits | None = None
    task_wrench: TaskWrench | None = None
    base_limits: BaseLimits | None = None
    grasp: GraspLimits | None = None
    unused_keys: tuple[str, ...] = ()           # UNUSED_TOP_LEVEL_KEYS present in the file

    @property
    def tipping(self) -> bool:
        return self.base_limits is not None and self.base_limits.support_polygon is not None

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (``None`` for unlimited) for evidence records."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        def vec(a: np.ndarray | None) -> list[float] | None:
            return None if a is None else [float(x) for x in a]

        b, g, w = self.base_limits, self.grasp, self.task_wrench
        return {
            "frame_limits": {f.frame: {"point": vec(f.point), **{
                k: num(getattr(f, k)) for k in FRAME_LIMIT_KEYS[1:]}} for f in self.frame_limits},
            "robot_limits": None if self.robot_limits is None else {
                "max_kinetic_energy": num(self.robot_limits.max_kinetic_energy)},
            "task_wrench": None if w is None else {
                "frame": w.frame, "force": vec(w.force), "torque": vec(w.torque)},
            "base_limits": None if b is None else {
                "max_force": num(b.max_force), "max_moment": num(b.max_moment),
                "base_mass": b.base_mass, "base_com": vec(b.base_com),
                "support_polygon": None if b.support_polygon is None
                else b.support_polygon.vertices.tolist()},
            "grasp": None if g is None else {
                "frame": g.frame, "normal_axis": vec(g.normal_axis),
                "friction_coefficient": g.friction_coefficient, "grip_force": g.grip_force,
                "faces": g.faces},
            "unused_keys": list(self.unused_keys),
        }


# --- locating the limits mapping -----------------------------------------------------------------

def check_top_level_keys(mapping: Mapping[str, Any], *, source: str,
                         node_parameters: bool = False) -> None:
    """Unknown top-level keys are errors (a misspelt section would switch a check off), with a
    suggestion. ``node_parameters``: the mapping is a node's ``ros__parameters``, where the
    joint-limit parser lets other node parameters stand beside the limits sections."""
    for key, value in mapping.items():
        if key not in LIMITS_FILE_KEYS:
            if node_parameters:
                continue
            raise ModelError(f"{source}: unknown top-level key '{key}'"
                             f"{did_you_mean(str(key), LIMITS_FILE_KEYS)}; a limits file holds "
                             f"{', '.join(sorted(LIMITS_FILE_KEYS))}",
                             code="limits_unknown_section")
        if key in UNUSED_TOP_LEVEL_KEYS:
            _number(value, f"{source}: {key}", minimum=0.0, strict=True)


def locate_limits(data: Any, *, source: str) -> tuple[Mapping[str, Any], str, bool]:
    """(the mapping holding the limits sections, where to say it is, whether it is a node's
    ``ros__parameters``) for a parsed limits file: the bare mapping, or the one node's
    ``<node>: ros__parameters:`` carrying a limits key. Its keys are not checked here."""
    if not isinstance(data, Mapping):
        raise ModelError(f"{source}: expected a mapping with a 'joint_limits:' or another limits "
                         "section at its top level", code="limits_no_joint_limits")
    if not set(data) & LIMITS_FILE_KEYS:
        nested = [(str(name), v["ros__parameters"]) for name, v in data.items()
                  if isinstance(v, Mapping) and isinstance(v.get("ros__parameters"), Mapping)
                  and set(v["ros__parameters"]) & LIMITS_FILE_KEYS]
        if len(nested) > 1:
            raise ModelError(f"{source}: several nodes' ros__parameters carry limits sections "
                             f"({', '.join(n for n, _ in nested)}); give a file with one",
                             code="limits_no_joint_limits")
        if nested:
            return nested[0][1], f"{source}: {nested[0][0]}.ros__parameters", True
    return data, source, False


def limits_mapping(data: Any, *, source: str) -> tuple[Mapping[str, Any], str]:
    """(the limits mapping, where it is) as :func:`locate_limits`, its top-level keys checked
    (:func:`check_top_level_keys`: no node parameters beside the task sections)."""
    mapping, where, _ = locate_limits(data, source=source)
    if not mapping:
        raise ModelError(f"{source}: the limits file is empty", code="limits_no_joint_limits")
    check_top_level_keys(mapping, source=where)
    return mapping, where


# --- values --------------------------------------------------------------------------------------

def _bad(where: str, what: str, value: Any, code: str = "limits_wrong_type") -> ModelError:
    return ModelError(f"{where} must be {what}, got {shown(value)}", code=code)


def _number(value: Any, where: str, *, minimum: float, strict: bool) -> float:
    """A finite number > minimum (``strict``) or ≥ minimum; bool and NaN are not numbers."""
    what = f"a finite number {'>' if strict else '≥'} {minimum:g}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _bad(where, what, value)
    x = _float(value)
    if not math.isfinite(x) or x < minimum or (strict and x == minimum):
        raise _bad(where, what, value, code="limits_bad_value")
    return x


def _float(x: int | float) -> float:
    """float(x), an integer too large for a float as inf (refused as not finite)."""
    try:
        return float(x)
    except OverflowError:
        return math.inf


def _limit(value: Any, where: str) -> float:
    # a zero maximum forbids the motion outright, which no slowdown fixes: for no limit, omit it
    return _number(value, where, minimum=0.0, strict=True)


def _vector(value: Any, where: str, *, nonzero: bool = False) -> np.ndarray:
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value)):
        raise _bad(where, "a list of 3 numbers", value)
    v = np.array([_float(x) for x in value], dtype=float)
    if not np.all(np.isfinite(v)):
        raise _bad(where, "3 finite numbers", value, code="limits_bad_value")
    if nonzero and not np.any(v):
        raise _bad(where, "a nonzero vector", value, code="limits_bad_value")
    return _frozen(v)


def _unit(value: Any, where: str) -> np.ndarray:
    """A nonzero 3-vector scaled to length 1; scaled by its largest component first, so that
    neither tiny (1e-320) nor huge (1e308) components under- or overflow the norm."""
    v = _vector(value, where, nonzero=True)
    w = v / np.max(np.abs(v))
    u = w / np.linalg.norm(w)
    if not (np.all(np.isfinite(u)) and abs(float(np.linalg.norm(u)) - 1.0) < 1e-12):
        raise _bad(where, "a direction (a vector that normalises to length 1)", value,
                   code="limits_bad_value")
    return _frozen(u)


def _frame(name: Any, frames: Sequence[str], where: str) -> str:
    if not isinstance(name, str) or not name:
        raise _bad(where, "a link name", name)
    if name not in frames:
        close = difflib.get_close_matches(name[:200], list(frames), n=3)
        listed = (f"close: {name_list(close)}" if close
                  else f"links: {name_list(frames)}")
        raise ModelError(f"{where}: frame '{escape(name)}' is not a link of the URDF ({listed})",
                         code="limits_unknown_frame")
    return name


def _entries(value: Any, keys: Sequence[str], where: str, *,
             required: Sequence[str] = ()) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise _bad(where, f"a mapping of {', '.join(keys)}", value, code="limits_bad_entry")
    unknown = [f"'{escape(str(key))}'{did_you_mean(str(key), keys)}"
               for key in value if key not in keys]
    if unknown:
        raise ModelError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(unknown[:20])}", code="limits_unknown_key")
    missing = [k for k in required if k not in value]
    if missing:
        raise ModelError(f"{where}: missing {', '.join(missing)}", code="limits_missing_key")
    return value


def _checks_nothing(where: str, keys: Sequence[str]) -> ModelError:
    return ModelError(f"{where} configures no check: give at least one of {', '.join(keys)}",
                      code="limits_empty_section")


# --- sections ------------------------------------------------------------------------------------

def _frame_limits(value: Any, frames: Sequence[str], where: str) -> tuple[FrameLimits, ...]:
    if not isinstance(value, Mapping) or not value:
        raise _bad(where, "a mapping of link names to their limits", value,
                   code="limits_bad_entry")
    out = []
    for frame, entries in value.items():
        at = f"{where}.{frame}"
        _frame(str(frame), frames, where)
        e = _entries(entries, FRAME_LIMIT_KEYS, at)
        maxima = {k: _limit(e[k], f"{at}.{k}") for k in FRAME_LIMIT_KEYS[1:] if k in e}
        if not maxima:
            raise _checks_nothing(at, FRAME_LIMIT_KEYS[1:])
        point = _vector(e["point"], f"{at}.point") if "point" in e else _frozen(np.zeros(3))
        out.append(FrameLimits(frame=str(frame), point=point, **maxima))
    return tuple(out)


def _robot_limits(value: Any, where: str) -> RobotLimits:
    e = _entries(value, ROBOT_LIMIT_KEYS, where)
    if not e:
        raise _checks_nothing(where, ROBOT_LIMIT_KEYS)
    return RobotLimits(max_kinetic_energy=_limit(e["max_kinetic_energy"],
                                                 f"{where}.max_kinetic_energy"))


def _task_wrench(value: Any, frames: Sequence[str], where: str) -> TaskWrench:
    e = _entries(value, TASK_WRENCH_KEYS, where, required=("frame",))
    if "force" not in e and "torque" not in e:
        raise _checks_nothing(where, ("force", "torque"))
    zero = _frozen(np.zeros(3))
    return TaskWrench(
        frame=_frame(e["frame"], frames, f"{where}.frame"),
        force=_vector(e["force"], f"{where}.force") if "force" in e else zero,
        torque=_vector(e["torque"], f"{where}.torque") if "torque" in e else zero)


def support_polygon(value: Any, where: str) -> SupportPolygon:
    """Validate [[x, y], …] (m, root z = 0 plane): ≥ 3 finite points, no repeated neighbours,
    convex and simple, either winding (made counter-clockwise). Collinear vertices are kept."""
    what = "a list of at least 3 [x, y] points"
    if (not isinstance(value, (list, tuple)) or len(value) < 3
            or any(not isinstance(p, (list, tuple)) or len(p) != 2
                   or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in p)
                   for p in value)):
        raise _bad(where, what, value, code="limits_bad_polygon")
    v = np.array([[_float(x) for x in p] for p in value], dtype=float)
    if not np.all(np.isfinite(v)):
        raise _bad(where, "finite points", value, code="limits_bad_polygon")
    e = np.roll(v, -1, axis=0) - v
    length = np.linalg.norm(e, axis=1)
    if np.any(length == 0):
        i = int(np.argmax(length == 0))
        raise ModelError(f"{where}: the point {v[i].tolist()} is repeated next to itself",
                         code="limits_bad_polygon")
    nxt = np.roll(e, -1, axis=0)
    cross = e[:, 0] * nxt[:, 1] - e[:, 1] * nxt[:, 0]
    dot = np.einsum("ij,ij->i", e, nxt)
    straight = np.abs(cross) <= 1e-12 * length * np.roll(length, -1)
    turns = np.where(straight, 0.0, np.sign(cross))
    area = 0.5 * float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
    winding = np.sum(np.arctan2(cross, dot)) / (2 * math.pi)
    if not np.any(turns):
        raise ModelError(f"{where}: the points are collinear (no area)", code="limits_bad_polygon")
    sign = 1.0 if area > 0 else -1.0
    against = np.flatnonzero((turns == -sign) | (straight & (dot < 0)))
    if against.size or abs(abs(winding) - 1.0) > 1e-9:
        at = (f": it turns the other way at {v[(against[0] + 1) % len(v)].tolist()}"
              if against.size else " (it crosses itself)")
        raise ModelError(f"{where} is not convex{at}", code="limits_bad_polygon")
    # here, not at import: the force laws load their compiled kernels, which a model without a
    # support polygon (every audit of joint_states alone) does not need
    from dyn_node.core.check.force_laws import SupportPolygon

    return SupportPolygon.from_ccw(v if area > 0 else v[::-1])


def _base_limits(value: Any, where: str) -> BaseLimits:
    e = _entries(value, BASE_LIMIT_KEYS, where)
    if not any(k in e for k in ("max_force", "max_moment", "support_polygon")):
        raise _checks_nothing(where, ("max_force", "max_moment", "support_polygon"))
    if "support_polygon" not in e and ("base_mass" in e or "base_com" in e):
        raise ModelError(f"{where}: base_mass and base_com are used only for tipping; give "
                         "support_polygon too (or remove them)", code="limits_missing_key")
    mass = _number(e.get("base_mass", 0.0), f"{where}.base_mass", minimum=0.0, strict=False)
    if mass > MAX_BASE_MASS_KG:
        raise _bad(f"{where}.base_mass", f"at most {MAX_BASE_MASS_KG:g} kg", mass,
                   code="limits_bad_value")
    if mass > 0 and "base_com" not in e:
        raise ModelError(f"{where}: base_mass {mass:g} kg needs base_com (its centre of mass in "
                         "the root frame, m)", code="limits_missing_key")
    return BaseLimits(
        max_force=_limit(e["max_force"], f"{where}.max_force") if "max_force" in e else math.inf,
        max_moment=(_limit(e["max_moment"], f"{where}.max_moment") if "max_moment" in e
                    else math.inf),
        base_mass=mass,
        base_com=_vector(e["base_com"], f"{where}.base_com") if "base_com" in e else (
            _frozen(np.zeros(3)) if "support_polygon" in e else None),
        support_polygon=(support_polygon(e["support_polygon"], f"{where}.support_polygon")
                         if "support_polygon" in e else None))


def _grasp(value: Any, frames: Sequence[str], where: str) -> GraspLimits:
    e = _entries(value, GRASP_KEYS, where, required=GRASP_KEYS)
    faces = e["faces"]
    if isinstance(faces, bool) or not isinstance(faces, int) or faces < 1:
        raise _bad(f"{where}.faces", "a whole number ≥ 1", faces)
    # μ = 0 is a frictionless grip: only a purely normal force is held
    mu = _number(e["friction_coefficient"], f"{where}.friction_coefficient", minimum=0.0,
                 strict=False)
    grip = _limit(e["grip_force"], f"{where}.grip_force")
    # the cone's radius μ·grip·faces, and its square in the slip law, must stay finite
    if not math.isfinite((mu * grip * faces) ** 2):
        raise ModelError(f"{where}.friction_coefficient: {mu:g} × grip_force {grip:g} N × faces "
                         f"{faces} is too large (the friction force overflows)",
                         code="limits_bad_value")
    return GraspLimits(frame=_frame(e["frame"], frames, f"{where}.frame"),
                       normal_axis=_unit(e["normal_axis"], f"{where}.normal_axis"),
                       friction_coefficient=mu, grip_force=grip, faces=faces)


def parse_task_limits(mapping: Any, *, frames: Sequence[str], source: str) -> TaskLimits:
    """Parse and validate the task-space sections of a parsed limits file (the bare mapping or
    the ``<node>: ros__parameters:`` form). ``frames``: the URDF's link names. ``joint_limits`` is
    left to :mod:`dyn_node.core.robot.limits`; unknown top-level keys are errors."""
    data, where = limits_mapping(mapping, source=source)
    frames = tuple(frames)
    parsers = {"frame_limits": lambda v, at: _frame_limits(v, frames, at),
               "robot_limits": _robot_limits,
               "task_wrench": lambda v, at: _task_wrench(v, frames, at),
               "base_limits": _base_limits, "grasp": lambda v, at: _grasp(v, frames, at)}
    kw: dict[str, Any] = {}
    problems: list[ModelError] = []
    for section, parse in parsers.items():
        if section in data:
            try:
                kw[section] = parse(data[section], f"{where}: {section}")
            except ModelError as exc:   # every section's first problem, in one error
                problems.append(exc)
    if len(problems) > 1:
        raise ModelError(f"{len(problems)} problems: " + "; ".join(map(str, problems)),
                         code=problems[0].code)
    if problems:
        raise problems[0]
    unused = tuple(sorted(k for k in data if k in UNUSED_TOP_LEVEL_KEYS))
    return TaskLimits(source=where, unused_keys=unused, **kw)


def check_tipping_gravity(limits: TaskLimits, gravity: Sequence[float], *, source: str) -> None:
    """Reject tipping (a ``support_polygon``) unless gravity (root frame, m/s²) is along the
    root's −z: the polygon lies in the root z = 0 plane, taken as the floor."""
    if not limits.tipping:
        return
    g = np.asarray(gravity, dtype=float)
    norm = float(np.linalg.norm(g))
    if not (np.all(np.isfinite(g)) and g[2] < 0
            and math.hypot(g[0], g[1]) <= VERTICAL_GRAVITY_TOLERANCE * norm):
        raise ModelError(
            f"{source}: base_limits.support_polygon: tipping needs gravity along the root's −z "
            f"(the support polygon lies in the root z = 0 plane, taken as the floor), but gravity "
            f"is {[float(x) for x in g]} m/s²; for a wall, ceiling or tilted mount remove "
            "support_polygon (max_force and max_moment still apply)", code="tipping_gravity")
