"""The robot model the settings ask for: a URDF parameter, a URDF file, a built-in model, or the
URDF received on the robot_description topic (in that order)."""
from __future__ import annotations

import hashlib
import json
import threading
import weakref
from collections import OrderedDict
from pathlib import Path

from dyn_node.errors import SettingsError
from dyn_node.core.robot.limits import LimitsText
from dyn_node.core.robot.limits_file import limits_sha256, read_limits_file
from dyn_node.core.robot.model import Payload, RobotModel, builtin_urdf, load_model
from dyn_node.core.robot.settings import Settings

# model -> the limits file text it was built from (identity keys: RobotModel has eq=False)
_LIMITS_TEXT: "weakref.WeakKeyDictionary[RobotModel, str]" = weakref.WeakKeyDictionary()


def limits_text(model: RobotModel | None) -> str | None:
    """The limits file text ``model`` was built from by :func:`build_model`; None: no limits
    file (or a model built elsewhere)."""
    return None if model is None else _LIMITS_TEXT.get(model)


def build_model(settings: Settings, topic_description: str = "", *,
                cache: "ModelCache | None" = None, limits_yaml: str | None = None) -> RobotModel:
    """The model variant the settings ask for; ``topic_description`` is the URDF received on the
    robot_description topic, used when no model parameter is set. Raises ModelError/SettingsError.
    ``cache``: reuse a model built earlier in this process from the same inputs (ModelCache).
    ``limits_yaml``: the limits file's text (a bag's record) instead of reading
    ``settings.limits_file``, which then only names it; the text used is :func:`limits_text`."""
    if settings.limits_file and limits_yaml is None:
        limits_yaml = read_limits_file(settings.limits_file)
    if cache is not None:
        return cache.build(settings, topic_description, limits_yaml=limits_yaml)
    model = _load(settings, topic_description,
                  None if limits_yaml is None else LimitsText(limits_yaml, settings.limits_file or "limits"))
    if limits_yaml is not None:
        _LIMITS_TEXT[model] = limits_yaml
    return model


def _load(settings: Settings, topic_description: str, limits: LimitsText | None) -> RobotModel:
    kw = dict(locked_joints=dict(settings.locked_joints), limits_yaml=limits,
              payload=Payload(settings.payload_mass, settings.payload_com, settings.payload_frame),
              gravity=settings.gravity)
    if settings.robot_description:
        return load_model(urdf=settings.robot_description, source="parameter:robot_description", **kw)
    if settings.robot_description_file:
        return load_model(urdf_file=settings.robot_description_file, **kw)
    if settings.robot_model:
        return load_model(builtin=settings.robot_model, **kw)
    if topic_description:
        return load_model(urdf=topic_description, source="topic:robot_description", **kw)
    raise SettingsError("no robot description: set robot_description, robot_description_file or "
                        "robot_model, or publish the robot_description topic", code="no_source")


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _file_sha256(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def model_cache_key(settings: Settings, topic_description: str = "", *,
                    limits_yaml: str | None = None) -> str:
    """Everything :func:`build_model` reads, contents included: the settings' model fields (paths
    too: they appear in the model's source and limit warnings), and the hashes of the URDF text
    and of the bytes of the URDF, limits (``limits_yaml`` when given) and built-in files. Raises
    OSError/ValueError when a file cannot be read (the build then reports it)."""
    fields = list(settings.model_key())
    fields[0] = _sha256(fields[0])  # the URDF text itself: its hash keeps the key small
    files = {"robot_description_file": settings.robot_description_file,
             "limits_file": settings.limits_file}
    hashes = {k: _file_sha256(v) for k, v in files.items() if v and k != "limits_file"}
    if limits_yaml is not None:
        hashes["limits_file"] = limits_sha256(limits_yaml)
    elif settings.limits_file:
        hashes["limits_file"] = limits_sha256(Path(settings.limits_file).read_bytes())
    doc = {"settings": fields, "topic": _sha256(topic_description) if topic_description else "",
           "files": hashes,
           "builtin": _sha256(builtin_urdf(settings.robot_model)) if settings.robot_model else ""}
    # JSON text, not a tuple: -0.0 and 0.0 (or 1 and 1.0) are equal tuple keys, not equal texts
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


class ModelCache:
    """Models built in this process, keyed by :func:`model_cache_key` (least recently used
    dropped beyond ``size``): a hit is the model a fresh build gives for the same inputs. Sharing
    one is safe: a RobotModel is immutable (variants are new objects) and each Dynamics copies
    its Pinocchio model and owns the data. For a process that builds the same robots bag after
    bag (a fleet worker); ``hits`` and ``misses`` count the lookups."""

    def __init__(self, size: int = 8):
        self.size = size
        self.hits = self.misses = 0
        self._models: OrderedDict[str, RobotModel] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._models)

    def get(self, key: str) -> RobotModel | None:
        with self._lock:
            model = self._models.get(key)
            if model is None:
                self.misses += 1
                return None
            self._models.move_to_end(key)
            self.hits += 1
            return model

    def put(self, key: str, model: RobotModel) -> None:
        with self._lock:
            self._models[key] = model
            self._models.move_to_end(key)
            while len(self._models) > self.size:
                self._models.popitem(last=False)

    def build(self, settings: Settings, topic_description: str = "", *,
              limits_yaml: str | None = None) -> RobotModel:
        """The cached model for these inputs, else a fresh build, cached (a failure never is).
        ``limits_yaml``: as :func:`build_model` (read here from the file when not given)."""
        if settings.limits_file and limits_yaml is None:
            limits_yaml = read_limits_file(settings.limits_file)
        try:
            key = model_cache_key(settings, topic_description, limits_yaml=limits_yaml)
        except (OSError, ValueError):  # a file that cannot be read: the build says so
            return build_model(settings, topic_description, limits_yaml=limits_yaml)
        model = self.get(key)
        if model is None:
            model = build_model(settings, topic_description, limits_yaml=limits_yaml)
            if _same_key(key, settings, topic_description, limits_yaml):  # no file changed meanwhile
                self.put(key, model)
        return model


def _same_key(key: str, settings: Settings, topic_description: str, limits_yaml: str | None) -> bool:
    try:
        return model_cache_key(settings, topic_description, limits_yaml=limits_yaml) == key
    except (OSError, ValueError):
        return False


__all__ = ["ModelCache", "build_model", "limits_text", "model_cache_key"]
