"""The robot model the settings ask for: a URDF parameter, a URDF file, a built-in model, or the
URDF received on the robot_description topic (in that order)."""
from __future__ import annotations

import hashlib
import json
import threading
from collections import OrderedDict
from pathlib import Path

from dyn_node.errors import SettingsError
from dyn_node.core.model import Payload, RobotModel, builtin_urdf, load_model
from dyn_node.core.settings import Settings


def build_model(settings: Settings, topic_description: str = "", *,
                cache: "ModelCache | None" = None) -> RobotModel:
    """The model variant the settings ask for; ``topic_description`` is the URDF received on the
    robot_description topic, used when no model parameter is set. Raises ModelError/SettingsError.
    ``cache``: reuse a model built earlier in this process from the same inputs (ModelCache)."""
    if cache is not None:
        return cache.build(settings, topic_description)
    kw = dict(locked_joints=dict(settings.locked_joints), limits_yaml=settings.limits_file or None,
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


def model_cache_key(settings: Settings, topic_description: str = "") -> str:
    """Everything :func:`build_model` reads, contents included: the settings' model fields (paths
    too: they appear in the model's source and limit warnings), and the hashes of the URDF text
    and of the bytes of the URDF, limits and built-in files. Raises OSError/ValueError when a
    file cannot be read (the build then reports it)."""
    fields = list(settings.model_key())
    fields[0] = _sha256(fields[0])  # the URDF text itself: its hash keeps the key small
    files = {"robot_description_file": settings.robot_description_file,
             "limits_file": settings.limits_file}
    doc = {"settings": fields, "topic": _sha256(topic_description) if topic_description else "",
           "files": {k: _file_sha256(v) for k, v in files.items() if v},
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

    def build(self, settings: Settings, topic_description: str = "") -> RobotModel:
        """The cached model for these inputs, else a fresh build, cached (a failure never is)."""
        try:
            key = model_cache_key(settings, topic_description)
        except (OSError, ValueError):  # a file that cannot be read: the build says so
            return build_model(settings, topic_description)
        model = self.get(key)
        if model is None:
            model = build_model(settings, topic_description)
            if _same_key(key, settings, topic_description):  # no file changed during the build
                self.put(key, model)
        return model


def _same_key(key: str, settings: Settings, topic_description: str) -> bool:
    try:
        return model_cache_key(settings, topic_description) == key
    except (OSError, ValueError):
        return False


__all__ = ["ModelCache", "build_model", "model_cache_key"]
