"""The live node's settings: one immutable value, validated as a whole.

The ROS adapter declares one parameter per :data:`PARAMETERS` entry, reads them into a
:class:`Settings` with :func:`settings_from_mapping`, and on a run-time change validates the whole
new set the same way, so an invalid value is rejected with a reason and nothing is half-applied.
This module is pure (no rclpy); the adapter turns :class:`ParamSpec` into ParameterDescriptors.
"""
from __future__ import annotations

import math
from dataclasses import Field, dataclass, field, fields, replace
from typing import Any, Callable, Mapping

from dyn_node.errors import SettingsError


ACCELERATION_SOURCES = ("finite_difference", "zero")


@dataclass(frozen=True)
class ParamSpec:
    """One ROS parameter: name, kind ('string'|'double'|'integer'|'bool'|'double_array'),
    default, inclusive range (None: no range), unit-bearing description, and whether it changes
    the model (so a change rebuilds the model variant)."""

    name: str
    kind: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    affects_model: bool = False
    #: a double_array's length (None: one value for every joint or one per joint, ≥ 1)
    size: int | None = 3


def parse_locked_joints(text: str) -> tuple[tuple[str, float], ...]:
    """'a, b=0.5' → (('a', 0.0), ('b', 0.5)); raises :class:`SettingsError` on bad entries."""
    out: list[tuple[str, float]] = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        name, _, value = item.partition("=")
        name = name.strip()
        if not name:
            raise SettingsError(f"locked_joints: entry '{item}' has no joint name", code="bad_parameter")
        try:
            pos = float(value) if value.strip() else 0.0
        except ValueError:
            raise SettingsError(f"locked_joints: position of '{name}' is not a number: '{value}'",
                                code="bad_parameter") from None
        if not math.isfinite(pos):
            raise SettingsError(f"locked_joints: position of '{name}' must be finite", code="bad_parameter")
        if any(n == name for n, _ in out):
            raise SettingsError(f"locked_joints: '{name}' is listed twice", code="bad_parameter")
        out.append((name, pos))
    return tuple(out)


def _param(kind: str, default: Any, description: str, low: float | None = None,
           high: float | None = None, *, affects_model: bool = False, name: str = "",
           parse: Callable[[Any], Any] | None = None, size: int | None = 3) -> Any:
    """A :class:`Settings` field that declares its ROS parameter (the one place its default is
    written). ``default`` is the parameter's value; the field holds it as settings do (arrays as
    tuples, ``parse(default)`` for a parsed text). ``name``: the ROS name where it is not the
    field's ('payload.mass' for payload_mass); ``size``: a double_array's length (None: any
    length ≥ 1, each value within [low, high])."""
    value = tuple(default) if kind == "double_array" else parse(default) if parse else default
    spec = dict(name=name, kind=kind, default=default, description=description, low=low, high=high,
                affects_model=affects_model, size=size)
    return field(default=value, metadata={"parameter": spec})


@dataclass(frozen=True)
class Settings:
    """Validated node settings (SI units). Each field declares its ROS parameter (the
    :data:`PARAMETERS` entry): field names are the parameter names with '.' → '_'."""

    robot_description: str = _param(
        "string", "", "URDF XML of the robot; first of the three model sources that is non-empty wins",
        affects_model=True)
    robot_description_file: str = _param("string", "", "path to a URDF file", affects_model=True)
    robot_model: str = _param(
        "string", "", "built-in model name (panda, ur5, planar_2link); if all three model sources are "
        "empty the node waits for the robot_description topic", affects_model=True)
    gravity: tuple[float, float, float] = _param(
        "double_array", [0.0, 0.0, -9.81], "gravity vector in the model's base frame (m/s², 3 values)",
        affects_model=True)
    locked_joints: tuple[tuple[str, float], ...] = _param(
        "string", "", "joints to lock, comma separated 'name' (locked at 0) or 'name=position' (rad|m); "
        "added to a built-in model's default locks", affects_model=True, parse=parse_locked_joints)
    limits_file: str = _param(
        "string", "", "joint limits YAML (ros2_control joint_limits format plus dyn_node keys) merged "
        "over the URDF limits; empty: URDF limits only", affects_model=True)
    payload_mass: float = _param("double", 0.0, "payload point mass (kg)", 0.0, 1000.0,
                                 affects_model=True, name="payload.mass")
    payload_com: tuple[float, float, float] = _param(
        "double_array", [0.0, 0.0, 0.0], "payload centre of mass in payload.frame (m, 3 values)",
        affects_model=True, name="payload.com")
    payload_frame: str = _param("string", "", "frame (link) carrying the payload; empty: the last link",
                                affects_model=True, name="payload.frame")
    include_friction: bool = _param(
        "bool", True, "add the URDF's viscous and Coulomb joint friction to the model torques")
    acceleration_source: str = _param(
        "string", "finite_difference", "how q̈ is estimated for inverse dynamics: finite_difference "
        "(of velocity on header stamps) or zero")
    acceleration_filter_hz: float = _param(
        "double", 0.0, "cut-off of the first-order low-pass on the acceleration estimate (Hz); "
        "0 = unfiltered", 0.0, 1.0e6)
    effort_warn_ratio: float = _param(
        "double", 0.9, "effort utilisation (|τ| / limit) above which effort is reported as WARN", 0.0, 1.0)
    residual_warn_ratio: float = _param(
        "double", 0.1, "RMS effort residual (measured − model) as a fraction of the effort limit above "
        "which the residual is reported as WARN", 0.0, 10.0)
    stale_timeout: float = _param(
        "double", 0.5, "joint_states older than this are STALE; also the largest stamp gap "
        "differentiated for the acceleration estimate (s)", 1.0e-3, 3600.0)
    diagnostics_period: float = _param("double", 1.0, "period of /diagnostics (s)", 1.0e-2, 3600.0)
    controller_status_period: float = _param("double", 0.1, "period of ~/controller_status (s)",
                                             1.0e-3, 3600.0)
    tracking_tolerance: float = _param(
        "double", 0.05, "largest |q − reference| before the controller status is 'deviating' (rad|m)",
        0.0, 100.0)
    sample_period: float = _param("double", 0.001, "sampling period of the trajectory feasibility check (s)",
                                  1.0e-5, 1.0)
    qos_depth: int = _param("integer", 100, "history depth of the joint_states subscription (messages)",
                            1, 100000)
    check_queue_depth: int = _param(
        "integer", 8, "question service calls (check, inverse dynamics, retime) waiting to be answered; "
        "one arriving when this many of its kind wait is answered 'accepted: false, reason: busy' "
        "(requests per service)", 1, 10000)
    # 50,000: the node still converts each request and response (rclpy), which pauses
    # joint_states in proportion: 20-34 ms at 50,000 points, 57-78 ms at 100,000 (docs/node.md)
    services_max_points: int = _param(
        "integer", 50000, "largest point (or state) count a question service answers; a larger "
        "request is answered at once 'accepted: false, reason: too_large' (points)", 1, 10000000,
        name="services.max_points")
    services_max_queue_age: float = _param(
        "double", 10.0, "a question service call that waited longer than this in its queue is "
        "answered 'accepted: false, reason: expired' without being computed: its caller has most "
        "likely given up (s; DynClient's default check timeout)", 1.0e-3, 3600.0,
        name="services.max_queue_age")
    allow_nonzero_velocity_at_trajectory_end: bool = _param(
        "bool", False, "mirrors joint_trajectory_controller's parameter of that name: a trajectory "
        "whose last point has a non-zero velocity is refused by the controller (false), so the "
        "check refuses it too; set it as your controller has it")
    retime_limit_margin: float = _param(
        "double", 0.9, "share of each limit the retimer's time-optimal pass (TOPP-RA) may use "
        "before the exact check; below 1 leaves room for tracking feedback on a real controller "
        "(0.9: dyn_sim's controller stays unsaturated on the demo's goals, docs/retime.md; "
        "~/retime_trajectory, gate.mode retime)", 0.05, 1.0, name="retime.limit_margin")
    # the momentum observer and contact detection (docs/OBSERVER.md): one value applies to every
    # joint, or one per joint in model order (the length is checked against the model)
    observer_gain: tuple[float, ...] = _param(
        "double_array", [50.0], "gain K of the momentum observer behind ~/external_torque (1/s; "
        "time constant 1/K; one value or one per joint)", 1.0e-3, 1.0e5, size=None)
    contact_threshold: tuple[float, ...] = _param(
        "double_array", [0.05], "|τ̂_ext| / effort limit above which a joint is in contact (held "
        "contact_min_duration; one value or one per joint)", 1.0e-6, 10.0, size=None)
    collision_threshold: tuple[float, ...] = _param(
        "double_array", [0.20], "|τ̂_ext| / effort limit above which a contact is a collision "
        "(one value or one per joint, each ≥ contact_threshold)", 1.0e-6, 10.0, size=None)
    contact_min_duration: float = _param(
        "double", 0.02, "how long a threshold must be exceeded on every sample before contact or "
        "collision is reported (s)", 0.0, 60.0)
    contact_frame: str = _param(
        "string", "", "frame (link) of ~/external_wrench, the wrench that best explains τ̂_ext; "
        "empty: the flange (last link)")

    @property
    def has_model_source(self) -> bool:
        return bool(self.robot_description or self.robot_description_file or self.robot_model)

    def model_key(self) -> tuple:
        """Everything the model depends on: equal keys mean the same model variant."""
        return (self.robot_description, self.robot_description_file, self.robot_model,
                self.gravity, self.locked_joints, self.limits_file, self.payload_mass,
                self.payload_com, self.payload_frame)

    def to_parameters(self) -> dict[str, Any]:
        """The parameter values (ROS names) these settings came from, for records and YAML."""
        out: dict[str, Any] = {}
        for spec in PARAMETERS:
            v = getattr(self, _FIELDS[spec.name])
            if spec.name == "locked_joints":
                v = format_locked_joints(v)
            elif isinstance(v, tuple):
                v = list(v)
            out[spec.name] = v
        return out


def _spec(f: Field) -> ParamSpec:
    """The parameter a :class:`Settings` field declares."""
    p = dict(f.metadata["parameter"])
    return ParamSpec(**{**p, "name": p["name"] or f.name})


PARAMETERS: tuple[ParamSpec, ...] = tuple(_spec(f) for f in fields(Settings))
SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMETERS}
MODEL_PARAMETERS = frozenset(p.name for p in PARAMETERS if p.affects_model)
_FIELDS: dict[str, str] = {p.name: f.name for p, f in zip(PARAMETERS, fields(Settings))}


def format_locked_joints(locks: tuple[tuple[str, float], ...]) -> str:
    return ", ".join(f"{n}={v!r}" for n, v in locks)


def _check(spec: ParamSpec, value: Any) -> Any:
    where = f"parameter '{spec.name}'"
    if spec.kind == "string":
        if not isinstance(value, str):
            raise SettingsError(f"{where} must be a string, got {type(value).__name__}", code="bad_parameter")
        return value
    if spec.kind == "bool":
        if not isinstance(value, bool):
            raise SettingsError(f"{where} must be true or false, got {value!r}", code="bad_parameter")
        return value
    if spec.kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise SettingsError(f"{where} must be an integer, got {value!r}", code="bad_parameter")
    elif spec.kind == "double":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"{where} must be a number, got {value!r}", code="bad_parameter")
        value = float(value)
        if not math.isfinite(value):
            raise SettingsError(f"{where} must be finite, got {value}", code="bad_parameter")
    elif spec.kind == "double_array":
        what = f"{spec.size} numbers" if spec.size is not None else "one or more numbers"
        try:
            vals = tuple(float(v) for v in value if not isinstance(v, (bool, str)))
        except TypeError:
            raise SettingsError(f"{where} must be {what}, got {value!r}", code="bad_parameter") from None
        if len(vals) != len(value) or (len(vals) != spec.size if spec.size is not None else not vals):
            raise SettingsError(f"{where} must be {what}, got {list(value)!r}", code="bad_parameter")
        if not all(math.isfinite(v) for v in vals):
            raise SettingsError(f"{where} must be finite, got {list(vals)}", code="bad_parameter")
        if any(spec.low is not None and v < spec.low or spec.high is not None and v > spec.high
               for v in vals):
            raise SettingsError(f"{where} = {list(vals)} has a value outside [{spec.low}, {spec.high}]",
                                code="bad_parameter")
        return vals
    if spec.low is not None and value < spec.low or spec.high is not None and value > spec.high:
        raise SettingsError(f"{where} = {value} is outside [{spec.low}, {spec.high}]", code="bad_parameter")
    return value


def settings_from_mapping(values: Mapping[str, Any], base: Settings | None = None) -> Settings:
    """Validate parameter values (ROS names → values) over ``base`` (default: the defaults).

    Raises :class:`SettingsError` for an unknown name, a wrong type, NaN/Inf, a value out of range,
    or an inconsistent combination; the message says which parameter and why.
    """
    kw: dict[str, Any] = {}
    for name, value in values.items():
        spec = SPECS.get(name)
        if spec is None:
            raise SettingsError(f"unknown parameter '{name}'", code="bad_parameter")
        value = _check(spec, value)
        if name == "locked_joints":
            value = parse_locked_joints(value)
        elif name == "acceleration_source" and value not in ACCELERATION_SOURCES:
            raise SettingsError(f"parameter 'acceleration_source' must be one of "
                                f"{', '.join(ACCELERATION_SOURCES)}, got '{value}'", code="bad_parameter")
        kw[_FIELDS[name]] = value
    out = replace(base or Settings(), **kw)
    _check_contact_thresholds(out)
    return out


def _check_contact_thresholds(s: Settings) -> None:
    """collision_threshold ≥ contact_threshold joint by joint, where the lengths pair up (one
    value, or the same count); per-joint lengths against the model are the ContactMonitor's."""
    a, b = s.contact_threshold, s.collision_threshold
    if len(a) != len(b) and len(a) != 1 and len(b) != 1:
        raise SettingsError(f"contact_threshold has {len(a)} values and collision_threshold {len(b)}: "
                            "give one value or one per joint for each", code="bad_parameter")
    n = max(len(a), len(b))
    if any(c > d for c, d in zip(a * n if len(a) == 1 else a, b * n if len(b) == 1 else b)):
        raise SettingsError(f"collision_threshold {list(b)} must be ≥ contact_threshold {list(a)} "
                            "on every joint", code="bad_parameter")

