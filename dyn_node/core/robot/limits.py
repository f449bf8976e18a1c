"""Joint limits: parsed from the URDF, merged with a ros2_control-style joint_limits YAML.

A missing limit is represented by ``inf`` (unlimited), never by zero. One rule for what a zero
means, applied alike by the feasibility check and the live monitor: a URDF ``velocity="0"`` /
``effort="0"`` is URDF's way of writing "not given" (unlimited); a YAML ``max_X: 0`` is a real
limit (only a value of exactly 0 satisfies it), reported as a model warning. Everything is in SI
units and in the model's joint order: rad or m for positions, rad/s, rad/s², rad/s³, N·m (or N for
prismatic joints), N·m/s, W, seconds for the RMS window.

Every accepted YAML key is either applied or documented as not a limit: ``k_position`` and
``k_velocity`` are gains of ros2_control's soft-limit controller (how hard it pushes back), not
bounds, so dyn_node accepts and ignores them (``IGNORED_YAML_KEYS``).
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from dyn_node.errors import ModelError
from dyn_node.io.safe_load import LoadError, load_yaml
from dyn_node.io.text import escape, name_list, shown
from dyn_node.core.robot.limits_file import read_limits_file
from dyn_node.core.robot.task_limits import check_top_level_keys, did_you_mean, locate_limits

#: Window used for the RMS (thermal) effort limit when the limits file gives none.
DEFAULT_RMS_WINDOW_S = 1.0

# ros2_control's joint_limits keys, then dyn_node's own extensions.
_ROS2_CONTROL_KEYS = {
    "has_position_limits": bool, "min_position": float, "max_position": float,
    "has_velocity_limits": bool, "max_velocity": float,
    "has_acceleration_limits": bool, "max_acceleration": float,
    "has_deceleration_limits": bool, "max_deceleration": float,
    "has_jerk_limits": bool, "max_jerk": float,
    "has_effort_limits": bool, "max_effort": float,
    "angle_wraps": bool,
    "has_soft_limits": bool, "k_position": float, "k_velocity": float,
    "soft_lower_limit": float, "soft_upper_limit": float,
}
_EXTENSION_KEYS = {
    "max_effort_rate": float, "max_rms_effort": float, "rms_window": float,
    "max_power": float, "effort_speed_curve": list, "armature": float,
}
LIMITS_YAML_KEYS: dict[str, type] = {**_ROS2_CONTROL_KEYS, **_EXTENSION_KEYS}
#: Kinds that ros2_control switches with a ``has_<kind>_limits`` flag.
_FLAGGED_KINDS = ("position", "velocity", "acceleration", "deceleration", "jerk", "effort")
#: Accepted (standard files carry them) but not limits: soft-limit controller gains.
IGNORED_YAML_KEYS = frozenset({"k_position", "k_velocity"})

#: The limit kinds dyn_node checks, in report order. ``deceleration`` is |q̈| where |q̇| is
#: decreasing (q̇·q̈ < 0), against ros2_control's ``max_deceleration``.
LIMIT_KINDS = ("position", "velocity", "acceleration", "deceleration", "jerk", "effort",
               "effort_rate", "rms_effort", "power", "effort_speed")


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits in model order; ``inf`` (or ``-inf`` for lower bounds) means unlimited.

    ``continuous`` marks joints without any position limit: URDF ``continuous`` joints and joints
    the YAML declares ``angle_wraps: true``.

    ``effort_speed_curve[i]`` is ``None`` or an (n, 2) array of (|speed| rad/s, max |effort| N·m)
    points with ascending speeds: the motor's torque-speed envelope, interpolated linearly and held
    constant beyond its last point.
    """

    names: tuple[str, ...]
    position_lower: np.ndarray
    position_upper: np.ndarray
    soft_lower: np.ndarray
    soft_upper: np.ndarray
    continuous: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    deceleration: np.ndarray
    jerk: np.ndarray
    effort: np.ndarray
    effort_rate: np.ndarray
    rms_effort: np.ndarray
    rms_window: np.ndarray
    power: np.ndarray
    armature: np.ndarray
    effort_speed_curve: tuple[np.ndarray | None, ...]
    warnings: tuple[str, ...] = field(default=())

    @property
    def nv(self) -> int:
        return len(self.names)

    def effort_envelope(self, speed: np.ndarray) -> np.ndarray:
        """Max |effort| allowed at joint speeds ``speed`` (…×nv rad/s), from the torque-speed curve.

        Joints without a curve get ``inf``. Broadcasts over leading dimensions.
        """
        speed = np.abs(np.asarray(speed, dtype=float))
        out = np.full(speed.shape, np.inf)
        for j, curve in enumerate(self.effort_speed_curve):
            if curve is not None:
                out[..., j] = np.interp(speed[..., j], curve[:, 0], curve[:, 1])
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (``None`` for unlimited) for evidence records and self-test output."""

        def arr(a: np.ndarray) -> list[float | None]:
            return [None if not math.isfinite(x) else float(x) for x in a]

        return {
            "names": list(self.names),
            "position_lower": arr(self.position_lower), "position_upper": arr(self.position_upper),
            "soft_lower": arr(self.soft_lower), "soft_upper": arr(self.soft_upper),
            "continuous": [bool(c) for c in self.continuous],
            "velocity": arr(self.velocity), "acceleration": arr(self.acceleration),
            "deceleration": arr(self.deceleration), "jerk": arr(self.jerk),
            "effort": arr(self.effort), "effort_rate": arr(self.effort_rate),
            "rms_effort": arr(self.rms_effort), "rms_window": arr(self.rms_window),
            "power": arr(self.power), "armature": arr(self.armature),
            "effort_speed_curve": [None if c is None else c.tolist() for c in self.effort_speed_curve],
            "warnings": list(self.warnings),
        }


def _float_attr(elem: ET.Element | None, name: str, where: str) -> float | None:
    if elem is None or elem.get(name) is None:
        return None
    try:
        return float(elem.get(name))
    except ValueError as exc:
        raise ModelError(f"URDF {where}: attribute {name}={elem.get(name)!r} is not a number",
                         code="urdf_bad_number") from exc


def limits_from_urdf(root: ET.Element, joint_names: Sequence[str]) -> JointLimits:
    """Read position, velocity and effort limits, soft limits and continuity from URDF joints."""
    # Only <robot>'s direct <joint> children: <transmission> elements also contain <joint name=…>
    # tags (UR5's do), and iterating the whole tree would let those shadow the real joints.
    by_name = {j.get("name"): j for j in root.findall("joint")}
    n = len(joint_names)
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    slo, shi = np.full(n, -np.inf), np.full(n, np.inf)
    vel, eff = np.full(n, np.inf), np.full(n, np.inf)
    cont = np.zeros(n, dtype=bool)
    for i, name in enumerate(joint_names):
        j = by_name[name]
        where = f"joint '{name}'"
        lim = j.find("limit")
        cont[i] = j.get("type") == "continuous"
        if not cont[i]:
            lower, upper = _float_attr(lim, "lower", where), _float_attr(lim, "upper", where)
            if lower is not None and upper is not None and not (lower == 0.0 and upper == 0.0):
                lo[i], hi[i] = lower, upper
        v = _float_attr(lim, "velocity", where)
        e = _float_attr(lim, "effort", where)
        # URDF writes 0 for "not given"; a zero maximum would forbid all motion, so treat it as absent.
        if v is not None and v > 0:
            vel[i] = v
        if e is not None and e > 0:
            eff[i] = e
        sc = j.find("safety_controller")
        s_lo, s_hi = _float_attr(sc, "soft_lower_limit", where), _float_attr(sc, "soft_upper_limit", where)
        if s_lo is not None:
            slo[i] = s_lo
        if s_hi is not None:
            shi[i] = s_hi
    inf = np.full(n, np.inf)
    return JointLimits(
        names=tuple(joint_names), position_lower=lo, position_upper=hi, soft_lower=slo,
        soft_upper=shi, continuous=cont, velocity=vel, acceleration=inf.copy(),
        deceleration=inf.copy(), jerk=inf.copy(),
        effort=eff, effort_rate=inf.copy(), rms_effort=inf.copy(),
        rms_window=np.full(n, DEFAULT_RMS_WINDOW_S), power=inf.copy(), armature=np.zeros(n),
        effort_speed_curve=(None,) * n)


@dataclass(frozen=True)
class LimitsText:
    """A limits file's text as read once, reported as ``where`` (its path): the node builds its
    model from these characters and records them in the bag, so no second read can differ."""

    text: str
    where: str


def read_limits_source(source: "str | Path | Mapping[str, Any] | LimitsText") -> tuple[Any, str]:
    """(the parsed YAML, where to say it is) of a limits path, YAML text, parsed mapping or
    :class:`LimitsText`."""
    where = "limits"
    if isinstance(source, Mapping):
        return source, where
    if isinstance(source, LimitsText):
        where, text = source.where, source.text
    else:
        text = str(source)
        p = Path(text)
        if "\n" not in text and (p.suffix in (".yaml", ".yml") or p.exists()):
            where, text = str(p), read_limits_file(p)
    try:
        return load_yaml(text), where
    except LoadError as exc:
        if exc.field:   # a value refused while read (an integer of 5,000 digits)
            raise ModelError(f"{where}: {exc}", code="limits_bad_value") from None
        raise ModelError(f"{where}: not valid YAML: {exc}", code="limits_bad_yaml") from None


def load_limits_yaml(source: str | Path | Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Parse a joint_limits YAML (path, YAML text or already-parsed mapping) into per-joint dicts.

    Accepts the ros2_control layout ``joint_limits: {joint: {...}}``, also nested under
    ``<node>: ros__parameters:``. Unknown keys and wrong types raise :class:`ModelError` naming the
    joint and key (with a suggestion for likely typos).
    """
    return parse_joint_limits(*read_limits_source(source))


def parse_joint_limits(data: Any, where: str) -> dict[str, dict[str, Any]]:
    """:func:`load_limits_yaml` of a parsed limits file reported as ``where``: every unknown key
    and bad value of the file in one :class:`ModelError` (the first one's code)."""
    mapping, where, node_parameters = locate_limits(data, source=where)
    if not isinstance(mapping.get("joint_limits"), Mapping):
        raise ModelError(f"{where}: expected a top-level 'joint_limits:' mapping of joint names",
                         code="limits_no_joint_limits")
    check_top_level_keys(mapping, source=where, node_parameters=node_parameters)
    out: dict[str, dict[str, Any]] = {}
    problems: list[ModelError] = []
    for joint, entries in mapping["joint_limits"].items():
        joint = str(joint)
        if not isinstance(entries, Mapping):
            problems.append(ModelError(f"joint_limits.{escape(joint)} must be a mapping of limit "
                                       "keys", code="limits_bad_entry"))
            continue
        clean: dict[str, Any] = {}
        for key, value in entries.items():
            if key not in LIMITS_YAML_KEYS:
                hint = did_you_mean(str(key), LIMITS_YAML_KEYS)
                problems.append(ModelError(f"joint_limits.{escape(joint)}: unknown key "
                                           f"'{escape(str(key))}'{hint}", code="limits_unknown_key"))
                continue
            try:
                clean[key] = _coerce(escape(joint), key, value)
            except ModelError as exc:
                problems.append(exc)
        out[joint] = clean
    raise_all(problems, where)
    return out


#: Problems of one file listed in its error at most (the rest counted).
PROBLEMS_SHOWN = 20


def raise_all(problems: Sequence[ModelError], where: str) -> None:
    """One :class:`ModelError` for every problem found in a file (``where``), with the first
    one's code; nothing when there is none."""
    if not problems:
        return
    if len(problems) == 1:
        raise ModelError(f"{where}: {problems[0]}", code=problems[0].code)
    listed = "; ".join(str(p) for p in problems[:PROBLEMS_SHOWN])
    more = f"; … and {len(problems) - PROBLEMS_SHOWN} more" if len(problems) > PROBLEMS_SHOWN else ""
    raise ModelError(f"{where}: {len(problems)} problems: {listed}{more}", code=problems[0].code)


#: Keys whose value must be > 0 and finite (``rms_window``: a window of 0 or ∞ s has no RMS),
#: and ≥ 0 and finite (``armature``: a negative rotor inertia makes M(q) indefinite).
_POSITIVE_KEYS = frozenset({"rms_window"})
_NON_NEGATIVE_KEYS = frozenset({"armature"})
#: The limits proper: a finite number ≥ 0 (0 is a real limit, warned about). A negative or
#: infinite one is refused: ``-.inf`` used to read as "no limit" (only has_*: false says that).
_LIMIT_KEYS = frozenset({"max_velocity", "max_acceleration", "max_deceleration", "max_jerk",
                         "max_effort", "max_effort_rate", "max_rms_effort", "max_power"})


def _coerce(joint: str, key: str, value: Any) -> Any:
    want = LIMITS_YAML_KEYS[key]
    bad = ModelError(f"joint_limits.{joint}.{key} must be {want.__name__}, got {shown(value)}",
                     code="limits_wrong_type")
    if want is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if want is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        try:
            x = float(value)
        except OverflowError:
            raise ModelError(f"joint_limits.{joint}.{key} is too large for a number "
                             f"({shown(value)})", code="limits_bad_value") from None
        if math.isnan(x):
            raise bad
        if key in _POSITIVE_KEYS and not (0 < x < math.inf):
            raise ModelError(f"joint_limits.{joint}.{key} must be a finite number > 0 s, got "
                             f"{shown(value)}", code="limits_bad_value")
        if key in _NON_NEGATIVE_KEYS and not (0 <= x < math.inf):
            raise ModelError(f"joint_limits.{joint}.{key} must be a finite number ≥ 0, got "
                             f"{shown(value)}", code="limits_bad_value")
        if key in _LIMIT_KEYS and not (0 <= x < math.inf):
            kind = key.removeprefix("max_")
            off = f" or set has_{kind}_limits: false" if kind in _FLAGGED_KINDS else ""
            raise ModelError(f"joint_limits.{joint}.{key} must be a finite number ≥ 0, got "
                             f"{shown(value)} (for no limit remove the key{off})", code="limits_bad_value")
        return x
    # effort_speed_curve: [[speed, effort], ...] with ascending speeds
    try:
        curve = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        curve = np.empty((0, 0))  # reported as a bad curve below, with the expected shape
    if (curve.ndim != 2 or curve.shape[1] != 2 or len(curve) < 1 or not np.all(np.isfinite(curve))
            or np.any(curve < 0) or np.any(np.diff(curve[:, 0]) <= 0)):
        raise ModelError(f"joint_limits.{joint}.effort_speed_curve must be a list of "
                         "[speed rad/s, effort N·m] pairs, non-negative, speeds strictly ascending",
                         code="limits_bad_curve")
    return curve


def _set_range(arrays: dict[str, np.ndarray], i: int, entry: Mapping[str, Any], flag: str,
               **keys: str) -> None:
    """A lower/upper pair of joint i from ``entry`` (``keys``: array name → YAML key, lower
    first): both unlimited when ``flag`` is false, else each given value."""
    for (target, key), unlimited in zip(keys.items(), (-np.inf, np.inf)):
        if entry.get(flag) is False:
            arrays[target][i] = unlimited
        elif key in entry:
            arrays[target][i] = entry[key]


def merge_limits(base: JointLimits, overrides: Mapping[str, Mapping[str, Any]],
                 where: str = "limits") -> JointLimits:
    """Apply parsed YAML overrides on top of URDF limits; YAML wins, ``has_*: false`` removes.

    A ``max_*`` given without its ``has_*`` flag is applied (the flag is implied); every ``has_*:
    false`` removes its limit, also one the URDF set (``has_soft_limits: false`` the URDF's soft
    limits). ``angle_wraps: true`` makes the joint continuous: no hard or soft position limit (a
    position limit given beside it is dropped, with a warning). Joints named in the YAML that the
    model lacks raise :class:`ModelError`.
    """
    idx = {n: i for i, n in enumerate(base.names)}
    unknown = sorted(set(overrides) - set(idx))
    if unknown:
        raise ModelError(f"{where}: joint_limits names joints the model does not have: "
                         f"{name_list(unknown)} (model joints: {name_list(base.names)})",
                         code="limits_unknown_joint")
    arrays = {k: getattr(base, k).copy() for k in (
        "position_lower", "position_upper", "soft_lower", "soft_upper", "continuous", "velocity",
        "acceleration", "deceleration", "jerk", "effort", "effort_rate", "rms_effort",
        "rms_window", "power", "armature")}
    curves = list(base.effort_speed_curve)
    notes: list[str] = []

    def flagged(entry: Mapping[str, Any], flag: str, key: str, target: str, i: int) -> None:
        if entry.get(flag) is False:
            arrays[target][i] = np.inf
        elif key in entry:
            arrays[target][i] = entry[key]

    for joint, e in overrides.items():
        i = idx[joint]
        _set_range(arrays, i, e, "has_position_limits", position_lower="min_position",
                   position_upper="max_position")
        _set_range(arrays, i, e, "has_soft_limits", soft_lower="soft_lower_limit",
                   soft_upper="soft_upper_limit")
        if e.get("angle_wraps") is True:
            given = [k for k in ("has_position_limits", "min_position", "max_position",
                                 "soft_lower_limit", "soft_upper_limit")
                     if k in e and e[k] is not False]
            if given:
                notes.append(f"{joint}: angle_wraps: true, so {', '.join(given)} "
                             "not applied (a wrapping joint has no position limit)")
            arrays["continuous"][i] = True
            for k, v in (("position_lower", -np.inf), ("position_upper", np.inf),
                         ("soft_lower", -np.inf), ("soft_upper", np.inf)):
                arrays[k][i] = v
        flagged(e, "has_velocity_limits", "max_velocity", "velocity", i)
        flagged(e, "has_acceleration_limits", "max_acceleration", "acceleration", i)
        flagged(e, "has_deceleration_limits", "max_deceleration", "deceleration", i)
        flagged(e, "has_jerk_limits", "max_jerk", "jerk", i)
        flagged(e, "has_effort_limits", "max_effort", "effort", i)
        for key, target in (("max_effort_rate", "effort_rate"), ("max_rms_effort", "rms_effort"),
                            ("rms_window", "rms_window"), ("max_power", "power"),
                            ("armature", "armature")):
            if key in e:
                arrays[target][i] = e[key]
        if "effort_speed_curve" in e:
            curves[i] = e["effort_speed_curve"]
    return replace(base, effort_speed_curve=tuple(curves), warnings=base.warnings + tuple(notes),
                   **arrays)


def check_limits(limits: JointLimits, gravity_load: np.ndarray | None = None) -> tuple[str, ...]:
    """Return human-readable warnings for suspicious limits (never silently used as-is).

    ``gravity_load`` is the largest |gravity torque| per joint seen over sample poses (N·m); an
    effort limit more than 1000× a joint's gravity load is likely a unit or placeholder error.
    """
    out: list[str] = []
    for i, n in enumerate(limits.names):
        if limits.position_lower[i] > limits.position_upper[i]:
            out.append(f"{n}: lower position limit {limits.position_lower[i]:g} > upper "
                       f"{limits.position_upper[i]:g}")
        if limits.soft_lower[i] > limits.soft_upper[i]:
            out.append(f"{n}: soft lower limit {limits.soft_lower[i]:g} > soft upper "
                       f"{limits.soft_upper[i]:g}")
        for kind in ("velocity", "acceleration", "deceleration", "jerk", "effort", "effort_rate",
                     "rms_effort", "power"):
            value = getattr(limits, kind)[i]
            if value == 0:
                # only a YAML max_X can be 0 here (a URDF 0 is "not given"); it is applied as set
                off = f" or set has_{kind}_limits: false" if kind in _FLAGGED_KINDS else ""
                out.append(f"{n}: {kind} limit 0 is not positive: applied as a real limit (any "
                           f"nonzero {kind.replace('_', ' ')} violates it); for no limit remove "
                           f"the key{off}")
            elif value <= 0:
                out.append(f"{n}: {kind} limit {value:g} is not positive")
        if gravity_load is not None and gravity_load[i] > 1e-2 and math.isfinite(limits.effort[i]):
            ratio = limits.effort[i] / gravity_load[i]
            if ratio > 1000:
                out.append(f"{n}: effort limit {limits.effort[i]:g} N·m is {ratio:.0f}× its largest "
                           f"gravity load {gravity_load[i]:.3g} N·m (unit or placeholder error?)")
    return tuple(out)
