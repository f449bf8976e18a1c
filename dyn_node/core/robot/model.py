"""The robot model: URDF → Pinocchio model with joint bookkeeping, limits, payload and gravity.

A :class:`RobotModel` is immutable: changing payload, gravity or limits returns a new model, so a
live node can build the replacement on the side and swap one reference atomically.

Frames: the payload's centre of mass is expressed in the named frame (a URDF link); gravity is a
vector in the world (root link) frame in m/s².
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pinocchio as pin

from dyn_node.errors import InputError, ModelError
from dyn_node.core.robot.limits import (JointLimits, check_limits, limits_from_urdf,
                                        merge_limits, parse_joint_limits, read_limits_source)
from dyn_node.core.robot.task_limits import (TASK_SECTIONS, TaskLimits, check_tipping_gravity,
                                             locate_limits, parse_task_limits)

DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
_PACKAGE_URDF_DIR = Path(__file__).resolve().parents[2] / "urdf"

#: Built-in models: name → (where the URDF lives, joints locked by default with their positions).
BUILTIN_MODELS: dict[str, tuple[str, dict[str, float]]] = {
    "planar_2link": ("package:planar_2link.urdf", {}),
    "panda": ("erd:panda_description/urdf/panda.urdf",
              {"panda_finger_joint1": 0.0, "panda_finger_joint2": 0.0}),
    "ur5": ("erd:ur_description/urdf/ur5_robot.urdf", {}),
}
DEFAULT_MODEL = "panda"

_SUPPORTED_JOINT_TYPES = {"revolute", "continuous", "prismatic", "fixed"}


@dataclass(frozen=True)
class Payload:
    """A point mass ``mass`` (kg) at ``com`` (m, in ``frame``); ``frame=""`` means the last link."""

    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frame: str = ""


@dataclass(frozen=True)
class JointSample:
    """One joint state in model order: q (rad|m), v (rad/s|m/s) or None, effort (N·m|N) or None.

    ``effort`` is None when no joint reported one; individual joints without a measurement are NaN.
    """

    q: np.ndarray
    v: np.ndarray | None
    effort: np.ndarray | None
    ignored: int = 0


def example_robot_data_dir() -> Path:
    """Where example-robot-data's robots are installed (it ships data only, no Python module).

    From PyPI (the .venv set-up) it lives under the wheel's ``cmeel.prefix``; in a colcon
    workspace rosdep installs ``ros-jazzy-example-robot-data``, found through the ament index.
    """
    try:
        dist = importlib.metadata.distribution("example-robot-data")
        path = Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")))
        if path.is_dir():
            return path
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        from ament_index_python.packages import get_package_share_directory

        path = Path(get_package_share_directory("example-robot-data")) / "robots"
        if path.is_dir():
            return path
    except Exception:  # not a ROS environment, or the package is not in the index
        pass
    raise ModelError("example-robot-data is not installed (pip: example-robot-data; ROS: "
                     "ros-jazzy-example-robot-data)", code="builtin_missing")


def builtin_urdf(name: str) -> str:
    """The URDF text of a built-in model."""
    if name not in BUILTIN_MODELS:
        raise ModelError(f"unknown built-in robot model '{name}' (known: "
                         f"{', '.join(sorted(BUILTIN_MODELS))})", code="unknown_builtin")
    where, _ = BUILTIN_MODELS[name]
    kind, rel = where.split(":", 1)
    path = _PACKAGE_URDF_DIR / rel if kind == "package" else example_robot_data_dir() / rel
    return path.read_text()


def urdf_hash(urdf: str) -> str:
    """SHA-256 of the URDF text: identifies the exact description a verdict was computed with."""
    return hashlib.sha256(urdf.encode("utf-8")).hexdigest()


def _check_numbers(elem: ET.Element | None, attrs: Sequence[str], where: str,
                   vector: bool = False) -> None:
    """Reject non-numeric attributes here, with the URDF location, before Pinocchio sees them."""
    if elem is None:
        return
    for a in attrs:
        text = elem.get(a)
        if text is None:
            continue
        parts = text.split()
        try:
            values = [float(x) for x in parts]
        except ValueError:
            values = []
        if not values or (vector and len(values) != 3) or (not vector and len(values) != 1) \
                or any(math.isnan(x) for x in values):
            raise ModelError(f"URDF {where}: attribute {a}={text!r} is not "
                             f"{'3 numbers' if vector else 'a number'}",
                             code="urdf_bad_number")


def _parse_urdf(urdf: str) -> ET.Element:
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError as exc:
        raise ModelError(f"robot description is not valid XML: {exc}", code="urdf_bad_xml") from exc
    if root.tag != "robot":
        raise ModelError(f"robot description's root element is <{root.tag}>, expected <robot>",
                         code="urdf_not_robot")
    joints = root.findall("joint")
    if not joints:
        raise ModelError("robot description has no <joint>", code="urdf_no_joints")
    links = {link.get("name") for link in root.findall("link")}
    for link in root.findall("link"):
        _check_numbers(link.find("inertial/mass"), ("value",), f"link '{link.get('name')}' <mass>")
        _check_numbers(link.find("inertial/inertia"), ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"),
                       f"link '{link.get('name')}' <inertia>")
        _check_numbers(link.find("inertial/origin"), ("xyz", "rpy"),
                       f"link '{link.get('name')}' <inertial><origin>", vector=True)
    for j in joints:
        name, jtype = j.get("name"), j.get("type")
        if jtype not in _SUPPORTED_JOINT_TYPES:
            raise ModelError(f"URDF joint '{name}' has type '{jtype}'; dyn_node supports "
                             f"{', '.join(sorted(_SUPPORTED_JOINT_TYPES))}", code="urdf_joint_type")
        for tag in ("parent", "child"):
            el = j.find(tag)
            if el is None or el.get("link") not in links:
                raise ModelError(f"URDF joint '{name}': <{tag}> names a link that does not exist"
                                 f" ({el.get('link') if el is not None else 'missing'!r})",
                                 code="urdf_bad_link")
        where = f"joint '{name}'"
        _check_numbers(j.find("limit"), ("lower", "upper", "effort", "velocity"), f"{where} <limit>")
        _check_numbers(j.find("dynamics"), ("damping", "friction"), f"{where} <dynamics>")
        _check_numbers(j.find("safety_controller"), ("soft_lower_limit", "soft_upper_limit",
                                                     "k_position", "k_velocity"),
                       f"{where} <safety_controller>")
        _check_numbers(j.find("origin"), ("xyz", "rpy"), f"{where} <origin>", vector=True)
        _check_numbers(j.find("axis"), ("xyz",), f"{where} <axis>", vector=True)
    return root


def _as_revolute(root: ET.Element) -> str:
    """URDF text with continuous joints turned into revolute ones.

    Pinocchio represents a continuous joint as (cos, sin) with nq = 2; as a revolute joint it has
    the same dynamics with nq = nv = 1, so q is the plain angle everywhere in dyn_node. Position
    limits are read from the original text, so the placeholder bounds written here are never used.
    """
    root = ET.fromstring(ET.tostring(root))
    for j in root.findall("joint"):
        if j.get("type") == "continuous":
            j.set("type", "revolute")
            lim = j.find("limit")
            if lim is None:
                lim = ET.SubElement(j, "limit", effort="0", velocity="0")
            lim.set("lower", "-1e10")
            lim.set("upper", "1e10")
    return ET.tostring(root, encoding="unicode")


# eq=False: fields hold NumPy arrays and Pinocchio models, so the generated __eq__/__hash__ would
# raise; identity semantics let a model be a dict key or an lru_cache argument.
@dataclass(frozen=True, eq=False)
class RobotModel:
    """A loaded robot: Pinocchio model (payload, gravity and armature applied) plus bookkeeping.

    ``joint_names`` is the model order used by every array in dyn_node. Build with
    :func:`load_model`; derive variants with :meth:`with_payload`, :meth:`with_gravity`,
    :meth:`with_limits`.
    """

    name: str
    urdf: str
    source: str
    urdf_hash: str
    joint_names: tuple[str, ...]
    locked_joints: Mapping[str, float]
    limits: JointLimits
    payload: Payload
    gravity: np.ndarray
    pin_model: pin.Model = field(repr=False)
    base_model: pin.Model = field(repr=False)  # reduced model without payload
    urdf_warnings: tuple[str, ...] = ()
    _index: Mapping[str, int] = field(repr=False, default_factory=dict)
    #: the limits file's frame_limits, robot_limits, task_wrench, base_limits and grasp
    task_limits: TaskLimits = field(default_factory=lambda: TaskLimits(source=""))

    @property
    def nv(self) -> int:
        return len(self.joint_names)

    @property
    def total_mass(self) -> float:
        """Mass of all moving and fixed bodies, payload included (kg)."""
        return float(sum(self.pin_model.inertias[i].mass for i in range(self.pin_model.njoints)))

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.urdf_warnings + self.limits.warnings

    @property
    def payload_frame(self) -> str:
        return self.payload.frame or self.last_link

    @property
    def last_link(self) -> str:
        """The default payload frame: the flange at the end of the chain.

        Start at the child link of the last actuated joint and follow fixed joints while the
        chain does not branch and the next link is massless (a pure frame), e.g. Panda's
        ``panda_link7`` → ``panda_link8`` (the flange; ``panda_hand`` has mass, so it stops there).
        """
        return _flange_link(self.urdf, self.joint_names[-1], tuple(self.locked_joints))

    def with_payload(self, payload: Payload) -> "RobotModel":
        """Same robot carrying ``payload`` instead of the current one; the URDF is not reparsed."""
        payload = _validate_payload(payload, self.base_model, self.last_link)
        return replace(self, payload=payload,
                       pin_model=_apply(self.base_model, payload, self.gravity, self.limits))

    def with_gravity(self, gravity: Sequence[float]) -> "RobotModel":
        g = _gravity_vector(gravity)
        check_tipping_gravity(self.task_limits, g, source=self.task_limits.source)
        return replace(self, gravity=g, pin_model=_apply(self.base_model, self.payload, g, self.limits))

    def with_limits(self, limits_yaml: str | Path | Mapping[str, Any] | None) -> "RobotModel":
        """Same robot with URDF limits merged with ``limits_yaml`` (None: URDF limits only)."""
        parsed = None if limits_yaml is None else read_limits_source(limits_yaml)
        limits, task = _limits_and_task(ET.fromstring(self.urdf), self.joint_names, parsed,
                                        self.base_model, self.gravity)
        return replace(self, limits=limits, task_limits=task,
                       pin_model=_apply(self.base_model, self.payload, self.gravity, limits))

    # --- joint bookkeeping -------------------------------------------------------------------
    def mapping(self, names: Sequence[str]) -> tuple[np.ndarray, int]:
        """Indices into ``names`` for each model joint, and how many input names were ignored.

        Input names the model lacks (locked or unknown joints) are ignored and counted. Raises
        :class:`InputError` for empty or duplicate names, no model joint, or missing model joints.
        """
        return _mapping(tuple(self.joint_names), tuple(self.locked_joints), tuple(names))

    def to_model_order(self, names: Sequence[str], position: Sequence[float],
                       velocity: Sequence[float] | None = None,
                       effort: Sequence[float] | None = None) -> JointSample:
        """Validate a (names, position, velocity, effort) joint state and reorder it.

        ``velocity``/``effort`` may be empty (not available). Position and velocity must be finite;
        effort may be NaN per joint ("not available", as joint_state_broadcaster publishes it).
        """
        n = len(names)
        if n == 0:
            raise InputError("joint state has no joint names", code="empty")
        for label, arr in (("position", position), ("velocity", velocity), ("effort", effort)):
            if arr is not None and len(arr) not in (0, n) or (label == "position" and len(arr) != n):
                raise InputError(f"joint state has {n} names but {len(arr)} {label} values",
                                 code="length_mismatch")
        idx, ignored = self.mapping(names)
        q = self._in_order(position, idx, "position")
        v = self._in_order(velocity, idx, "velocity") if velocity is not None and len(velocity) else None
        e = None
        if effort is not None and len(effort):
            e = self._in_order(effort, idx, "effort", nan_ok=True)
            if np.all(np.isnan(e)):
                e = None
        return JointSample(q=q, v=v, effort=e, ignored=ignored)

    def _in_order(self, values: Sequence[float], idx: np.ndarray, label: str, *,
                  nan_ok: bool = False) -> np.ndarray:
        """``values`` taken at ``idx`` (model order); InputError naming the joints whose value is
        not finite (``nan_ok``: only infinite ones, NaN meaning "not available")."""
        x = np.asarray(values, dtype=float)[idx]
        bad = np.isinf(x) if nan_ok else ~np.isfinite(x)
        if bad.any():
            joints = ", ".join(self.joint_names[i] for i in np.flatnonzero(bad))
            raise InputError(f"{'infinite' if nan_ok else 'non-finite'} {label} for {joints}",
                             code="non_finite")
        return x


@lru_cache(maxsize=256)
def _mapping(model_names: tuple[str, ...], locked: tuple[str, ...],
             names: tuple[str, ...]) -> tuple[np.ndarray, int]:
    # Cached: a publisher almost always sends the same name list, so the hot path is a dict hit.
    if not names:
        raise InputError("joint state has no joint names", code="empty")
    if len(set(names)) != len(names):
        dups = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"duplicate joint names: {', '.join(dups)}", code="duplicate_names")
    pos = {n: i for i, n in enumerate(names)}
    present = [n for n in model_names if n in pos]
    if not present:
        raise InputError(f"none of the model's joints ({', '.join(model_names)}) is in the message "
                         f"(got {', '.join(names[:8])}{' …' if len(names) > 8 else ''})",
                         code="no_model_joints")
    missing = [n for n in model_names if n not in pos]
    if missing:
        raise InputError(f"model joints missing from the message: {', '.join(missing)}",
                         code="missing_joints")
    idx = np.array([pos[n] for n in model_names], dtype=np.intp)
    idx.setflags(write=False)
    return idx, len(names) - len(model_names)


@lru_cache(maxsize=32)
def _flange_link(urdf: str, last_joint: str, locked: tuple[str, ...]) -> str:
    root = ET.fromstring(urdf)
    joints = root.findall("joint")
    link = next((j.find("child").get("link") for j in joints if j.get("name") == last_joint), None)
    if link is None:  # pragma: no cover - joint names come from this URDF
        raise ModelError(f"joint '{last_joint}' not in the URDF", code="no_joints")
    masses = {}
    for el in root.findall("link"):
        m = el.find("inertial/mass")
        masses[el.get("name")] = float(m.get("value", "0")) if m is not None else 0.0
    for _ in range(len(joints)):
        children = [j for j in joints if j.find("parent").get("link") == link]
        if len(children) != 1:
            break
        j = children[0]
        nxt = j.find("child").get("link")
        if (j.get("type") != "fixed" and j.get("name") not in locked) or masses.get(nxt, 0.0) > 0:
            break
        link = nxt
    return link


def _gravity_vector(gravity: Sequence[float]) -> np.ndarray:
    try:
        g = np.array(gravity, dtype=float)
    except (TypeError, ValueError):
        g = np.full(1, np.nan)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ModelError(f"gravity must be 3 finite numbers (m/s²), got {gravity!r}",
                         code="bad_gravity")
    g.setflags(write=False)
    return g


def _apply(base: pin.Model, payload: Payload, gravity: np.ndarray, limits: JointLimits) -> pin.Model:
    """A copy of ``base`` with payload inertia, gravity and armature applied."""
    m = base.copy()
    m.gravity.linear = np.array(gravity, dtype=float)
    m.armature = np.array(limits.armature, dtype=float)
    if payload.mass != 0.0:
        frame = payload.frame
        if not frame or not m.existFrame(frame):
            raise ModelError(f"payload frame '{frame}' is not a frame of the model", code="bad_frame")
        f = m.frames[m.getFrameId(frame)]
        com_in_joint = f.placement.act(np.asarray(payload.com, dtype=float))
        m.inertias[f.parentJoint] = m.inertias[f.parentJoint] + pin.Inertia(
            float(payload.mass), com_in_joint, np.zeros((3, 3)))
    return m


def _validate_payload(payload: Payload, model: pin.Model, default_frame: str) -> Payload:
    com = tuple(float(c) for c in payload.com)
    if not math.isfinite(payload.mass) or payload.mass < 0:
        raise ModelError(f"payload mass must be a finite number ≥ 0 kg, got {payload.mass}",
                         code="bad_payload")
    if len(com) != 3 or not all(math.isfinite(c) for c in com):
        raise ModelError(f"payload com must be 3 finite numbers (m), got {payload.com}",
                         code="bad_payload")
    frame = payload.frame or default_frame
    if not model.existFrame(frame):
        raise ModelError(f"payload frame '{frame}' is not a link of the model", code="bad_frame")
    return Payload(mass=float(payload.mass), com=com, frame=frame)  # type: ignore[arg-type]


def _gravity_load(model: pin.Model, limits: JointLimits, samples: int = 32) -> np.ndarray:
    """Largest |g(q)| per joint over seeded poses inside the position limits (N·m)."""
    rng = np.random.default_rng(0)
    lo = np.where(np.isfinite(limits.position_lower), limits.position_lower, -np.pi)
    hi = np.where(np.isfinite(limits.position_upper), limits.position_upper, np.pi)
    # Inverted limits are reported by check_limits; sampling must still work to get there.
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    data = model.createData()
    worst = np.zeros(model.nv)
    for _ in range(samples):
        q = rng.uniform(lo, hi)
        worst = np.maximum(worst, np.abs(pin.computeGeneralizedGravity(model, data, q)))
    return worst


def _build_limits(root: ET.Element, joint_names: Sequence[str],
                  parsed: tuple[Any, str] | None, model: pin.Model) -> JointLimits:
    """URDF limits merged with the parsed limits file (``read_limits_source``'s (data, where))."""
    limits = limits_from_urdf(root, joint_names)
    if parsed is not None:
        limits = merge_limits(limits, parse_joint_limits(*parsed), where=parsed[1])
    m = model.copy()
    m.armature = np.zeros(m.nv)
    # merge notes (what the YAML asked for and was not applied) first, then suspicious values
    return replace(limits, warnings=limits.warnings + check_limits(limits, _gravity_load(m, limits)))


def _limits_and_task(root: ET.Element, joint_names: Sequence[str], parsed: tuple[Any, str] | None,
                     model: pin.Model, gravity: np.ndarray) -> tuple[JointLimits, TaskLimits]:
    """:func:`_build_limits` and :func:`_task_limits`; the problems of both in one error."""
    out, problems = [], []
    for build in (lambda: _build_limits(root, joint_names, parsed, model),
                  lambda: _task_limits(parsed, model, gravity)):
        try:
            out.append(build())
        except ModelError as exc:
            if all(str(exc) != str(p) for p in problems):   # a top-level key both refuse
                problems.append(exc)
    if len(problems) > 1:
        raise ModelError("; ".join(map(str, problems)), code=problems[0].code)
    if problems:
        raise problems[0]
    return out[0], out[1]


def _task_limits(parsed: tuple[Any, str] | None, model: pin.Model, gravity: np.ndarray) -> TaskLimits:
    """The task sections of the parsed limits file (frames: the model's), tipping's gravity
    checked. A file without any keeps loading as before: node parameters may stand beside
    joint_limits in ros__parameters (a bare file's unknown keys are refused by the joint-limit
    parser, which runs first)."""
    if parsed is None:
        return TaskLimits(source="")
    data, where = parsed
    if not any(k in TASK_SECTIONS for k in locate_limits(data, source=where)[0]):
        return TaskLimits(source="")
    task = parse_task_limits(data, frames=[f.name for f in model.frames], source=where)
    check_tipping_gravity(task, gravity, source=task.source)
    return task


def load_model(*, urdf: str | None = None, urdf_file: str | Path | None = None,
               builtin: str | None = None, locked_joints: Mapping[str, float] | None = None,
               limits_yaml: str | Path | Mapping[str, Any] | None = None,
               payload: Payload = Payload(), gravity: Sequence[float] = DEFAULT_GRAVITY,
               source: str | None = None) -> RobotModel:
    """Load a robot from exactly one of a URDF string, a URDF file or a built-in name.

    ``locked_joints`` maps joint names to the fixed position (rad|m) at which the reduced model is
    built; a built-in model's default locks (Panda's fingers at 0 m) apply unless overridden.
    Raises :class:`ModelError` with what is wrong and where.
    """
    given = [x for x in (urdf, urdf_file, builtin) if x]
    if len(given) != 1:
        raise ModelError("give exactly one of a URDF string, a URDF file or a built-in model name",
                         code="no_source")
    locks: dict[str, float] = {}
    if builtin:
        text = builtin_urdf(builtin)
        locks.update(BUILTIN_MODELS[builtin][1])
        src = source or f"builtin:{builtin}"
    elif urdf_file:
        p = Path(urdf_file)
        if not p.is_file():
            raise ModelError(f"URDF file {p} does not exist", code="urdf_file_missing")
        text = p.read_text()
        src = source or f"file:{p}"
    else:
        text = str(urdf)
        src = source or "string"
    locks.update(locked_joints or {})
    root = _parse_urdf(text)
    try:
        full = pin.buildModelFromXML(_as_revolute(root))
    except Exception as exc:  # Pinocchio raises RuntimeError/ValueError with its own text
        raise ModelError(f"Pinocchio could not build a model from the robot description: {exc}",
                         code="urdf_pinocchio") from exc
    unknown = [n for n in locks if not full.existJointName(n)]
    if unknown:
        raise ModelError(f"locked_joints names joints the model does not have: {', '.join(unknown)}",
                         code="unknown_locked_joint")
    for n, v in locks.items():
        if not math.isfinite(v):
            raise ModelError(f"locked joint '{n}' position must be finite, got {v}", code="bad_lock")
    q_ref = pin.neutral(full)
    lock_ids = []
    for n, v in locks.items():
        jid = full.getJointId(n)
        q_ref[full.joints[jid].idx_q] = v
        lock_ids.append(jid)
    base = pin.buildReducedModel(full, lock_ids, q_ref) if lock_ids else full
    if base.nv == 0:
        raise ModelError("the model has no actuated joint left", code="no_joints")
    if base.nq != base.nv:  # pragma: no cover - _as_revolute removes the only nq != nv case we allow
        raise ModelError("only single-DoF joints are supported", code="urdf_joint_type")
    names = tuple(base.names[i] for i in range(1, base.njoints))
    g = _gravity_vector(gravity)
    parsed = None if limits_yaml is None else read_limits_source(limits_yaml)
    limits, task = _limits_and_task(root, names, parsed, base, g)
    model = RobotModel(
        name=root.get("name") or "robot", urdf=text, source=src, urdf_hash=urdf_hash(text),
        joint_names=names, locked_joints=dict(locks), limits=limits, payload=Payload(), gravity=g,
        pin_model=base, base_model=base, urdf_warnings=(),
        _index={n: i for i, n in enumerate(names)}, task_limits=task)
    payload = _validate_payload(payload, base, model.last_link)
    return model.with_payload(payload)


def model_from_source(robot_description: str = "", robot_description_file: str = "",
                      robot_model: str = "", **kwargs: Any) -> RobotModel:
    """Load from the node's three model parameters; the first non-empty one wins."""
    if robot_description:
        return load_model(urdf=robot_description, **kwargs)
    if robot_description_file:
        return load_model(urdf_file=robot_description_file, **kwargs)
    if robot_model:
        return load_model(builtin=robot_model, **kwargs)
    raise ModelError("no robot description given", code="no_source")
