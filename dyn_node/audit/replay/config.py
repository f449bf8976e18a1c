"""dyn-audit's stage 1: open the bag and resolve the configurations of the node that recorded it,
from its ``dyn_node`` metadata records (the first one, then each change from the log time it took
effect), with the command line's overrides. Rules: docs/BAGS.md."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dyn_node.audit.evidence import jsonable, task_limits_section
from dyn_node.audit.options import AuditError, AuditOptions
from dyn_node.bag.metadata import LIMITS_SHA256_KEY, LIMITS_YAML_KEY
from dyn_node.io.safe_load import load_yaml
from dyn_node.bag.reader import BagMessage, BagReader, MessageDecoder
from dyn_node.errors import DynNodeError


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(tree, dict):
        for k, v in tree.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if isinstance(v, dict):
                out.update(_flatten(v, key))
            else:
                out[key] = v
    return out


def parameters_from_yaml(text: str) -> dict[str, Any]:
    """Node parameters from a --params-file YAML (``{node: {ros__parameters: {...}}}``) or a flat
    mapping; nested keys are joined with '.'. Read by the project's bounded, strict loader: a
    malformed file (a 4,301-digit integer, duplicate keys) raises its LoadError, one line."""
    doc = load_yaml(text) if text else None
    if not isinstance(doc, dict):
        return {}
    for v in doc.values():
        if isinstance(v, dict) and "ros__parameters" in v:
            return _flatten(v["ros__parameters"])
    if "ros__parameters" in doc:
        return _flatten(doc["ros__parameters"])
    return _flatten(doc)


@dataclass
class Config:
    """One configuration of the recording node, as replayed: from ``since_ns`` (log time; None:
    from the start) until the next one. ``not_comparable``: how it differs from the node's."""

    settings: Any
    model: Any
    parameters: dict
    since_ns: int | None
    not_comparable: list[str]


def recorded_limits(meta: dict, path: str, findings: list[str]) -> str:
    """The limits text a metadata record carries (the node's model was built from it); a
    finding when its sha256 does not match the record's or the file at ``path`` differs."""
    from dyn_node.core.robot.limits_file import limits_sha256

    text = meta[LIMITS_YAML_KEY]
    sha = limits_sha256(text)
    if meta.get(LIMITS_SHA256_KEY, sha) != sha:
        findings.append(f"the bag's limits text has sha256 {sha}, its record says "
                        f"{meta[LIMITS_SHA256_KEY]}: the text is used")
    try:
        disk = limits_sha256(Path(path).read_bytes()) if path else sha
    except OSError:  # moved or deleted since: the recorded text is all that is needed
        disk = sha
    if disk != sha:
        findings.append(f"the limits file {path} on this machine (sha256 {disk}) differs from the "
                        f"text the node read (sha256 {sha}): the bag's recorded text is used")
    return text


def limits_source(settings: Any, overrides: dict[str, Any], recorded: bool, missing: str) -> str:
    """Where the replayed limits come from, as the evidence's configuration.model names it."""
    if "limits" in overrides:
        return f"override:{overrides['limits']}"
    if recorded:
        return "bag:limits_yaml"
    if missing:
        return f"urdf ({missing} not recorded, not on this machine)"
    if settings.limits_file:
        return f"file:{settings.limits_file} (not recorded: older recorder)"
    return "urdf"


def task_limits_differences(recorded: Any, used: Any) -> list[str]:
    """The task sections (frame_limits, …, grasp) that differ between the two models' limits."""
    a, b = task_limits_section(recorded) or {}, task_limits_section(used) or {}
    changed = sorted(k for k in set(a) | set(b) if k != "unused_keys"
                     and jsonable(a.get(k)) != jsonable(b.get(k)))
    return ["task limits: " + ", ".join(changed)] if changed else []


def model_differences(recorded: Any, used: Any) -> list[str]:
    """What differs between the model the node used and the one the audit uses (empty: none)."""
    out = []
    rj, uj = list(recorded.joint_names), list(used.joint_names)
    if rj != uj:
        extra = [n for n in uj if n not in rj]
        gone = [n for n in rj if n not in uj]
        out.append(f"joints: {len(rj)} recorded, {len(uj)} here"
                   + (f" (here only: {', '.join(extra)})" if extra else "")
                   + (f" (recorded only: {', '.join(gone)})" if gone else ""))
    if dict(recorded.locked_joints) != dict(used.locked_joints):
        out.append(f"locked joints: recorded {', '.join(recorded.locked_joints) or 'none'}; "
                   f"here {', '.join(used.locked_joints) or 'none'}")
    if recorded.urdf_hash != used.urdf_hash:
        out.append(f"URDF: recorded sha256 {recorded.urdf_hash[:12]}, here {used.urdf_hash[:12]}")
    if rj == uj:  # limits are per joint: with other joints, every one differs
        a, b = recorded.limits.to_dict(), used.limits.to_dict()
        changed = sorted(k for k in set(a) | set(b) if jsonable(a.get(k)) != jsonable(b.get(k)))
        if changed:
            out.append("limits: " + ", ".join(changed))
    out += task_limits_differences(recorded, used)
    if recorded.payload.mass != used.payload.mass:
        out.append(f"payload mass: recorded {recorded.payload.mass:g} kg, here {used.payload.mass:g} kg")
    if list(recorded.gravity) != list(used.gravity):
        out.append("gravity")
    return out



class Configurator:
    """Reads the bag's configurations (:meth:`read`); ``findings`` collects what the later stages
    report (shared with them through :class:`AuditSource`)."""

    def __init__(self, opts: AuditOptions, decoder: MessageDecoder, findings: list[str]):
        self.opts = opts
        self.decoder = decoder
        self.findings = findings

    def read(self) -> "AuditSource":
        """Open the bag and resolve the configurations to replay under."""
        reader = open_bag(self.opts.bag)
        self._configure(reader)
        return AuditSource(reader, self.configurations, self.overrides, self.model_source,
                           self.bag_metadata_version, self.findings, self.limits_source)

    def _configure(self, reader: BagReader) -> None:
        """The configurations to replay: the first ``dyn_node`` metadata record's, then each
        later one from the log time it took effect (``effective_log_time_ns``)."""
        records = reader.metadata_records("dyn_node")
        if not records:
            # Every record damaged (reported as unreadable when streamed): its fields that still
            # decode are the only trace of the node's parameters; a description that does not
            # decode comes from the /robot_description copy instead.
            for good, bad in reader.damaged_metadata_records("dyn_node")[:1]:
                records = [good]
                self.findings.append("the dyn_node metadata record is damaged (not UTF-8: "
                                     + ", ".join(bad) + "): its other fields are used"
                                     + (", the description from /robot_description"
                                        if "robot_description" in bad else ""))
        meta = records[0] if records else {}
        self.bag_metadata_version = meta.get("version")
        topic_desc = ""
        if not meta.get("robot_description", ""):
            m = self._peek_description(reader)
            if m is not None:
                try:
                    topic_desc = self.decoder.decode(m.channel, m.data).data
                except Exception:  # noqa: BLE001 - an undecodable description is simply absent
                    topic_desc = ""
        first = self._resolve(meta, topic_desc, first=True)
        self.configurations = [first] + self._changes(records[1:], meta, topic_desc, first)

    def _changes(self, records: list[dict], first_meta: dict, topic_desc: str,
                 first: "Config") -> list["Config"]:
        """Later configurations in the order they took effect. Each new ``effective_log_time_ns``
        is a core the node rebuilt (even for a value set to what it was: the monitor's state
        starts afresh); the same time again (a split file's copy, or parameters the node does not
        use) is the same core. A record without the time (older recorders) cannot be placed."""
        first_since = _effective_ns(first_meta)
        timed: dict[int, dict] = {}
        untimed = 0
        prev = first_meta
        for meta in records:
            keys = ("parameters", "robot_description", LIMITS_YAML_KEY)
            changed = tuple(map(meta.get, keys)) != tuple(map(prev.get, keys))
            prev = meta
            since = _effective_ns(meta)
            if since is None:
                untimed += changed
            elif since != first_since:
                timed[since] = meta  # the last record for a moment is the complete snapshot
        out: list[Config] = []
        for since in sorted(timed):
            cfg = self._resolve(timed[since], topic_desc, first=False, since_ns=since)
            if cfg.model.joint_names != first.model.joint_names:
                first.not_comparable.append(f"the model's joints change at log time {since} ns "
                                            "(not replayed: the first configuration is kept)")
                self.findings.append(f"configuration at log time {since} ns changes the model's "
                                     "joints: not replayed")
                continue
            out.append(cfg)
        if untimed:
            first.not_comparable.append(f"{untimed} configuration change(s) recorded without the "
                                        "time they took effect (older recorder): not replayed")
            self.findings.append(f"{untimed} configuration change(s) in the bag carry no "
                                 "effective_log_time_ns: replayed with the first configuration")
        return out

    def _bag_settings(self, meta: dict, topic_desc: str, findings: list[str], *,
                      overrides_on: bool) -> tuple[Any, dict[str, Any], str, str | None]:
        """(settings, overrides applied, the bag's limits_file when it is not on this machine,
        the limits text the record carries) for one metadata record; ``overrides_on=False``:
        what the node itself used."""
        from dataclasses import replace

        from dyn_node.errors import SettingsError
        from dyn_node.core.robot.settings import SPECS, Settings, settings_from_mapping

        params = parameters_from_yaml(meta.get("parameters", ""))
        known = {k: v for k, v in params.items() if k in SPECS}
        try:
            settings = settings_from_mapping(known)
        except SettingsError as exc:
            findings.append(f"bag parameters rejected ({exc}); defaults used")
            settings = Settings()
        overrides: dict[str, Any] = {}
        desc_in_bag = meta.get("robot_description", "")
        if overrides_on and self.opts.robot_description:
            p = Path(self.opts.robot_description)
            if not p.is_file():
                raise AuditError(f"robot description file {p} does not exist", code="no_model")
            settings = replace(settings, robot_description=p.read_text(), robot_description_file="",
                               robot_model="")
            overrides["robot_description"] = str(p)
        elif overrides_on and self.opts.robot_model:
            settings = replace(settings, robot_description="", robot_description_file="",
                               robot_model=self.opts.robot_model)
            overrides["robot_model"] = self.opts.robot_model
        elif settings.robot_model and not settings.robot_description:
            # A built-in model ships with the package; check it is the one the bag recorded.
            from dyn_node.core.robot.model import BUILTIN_MODELS, builtin_urdf, urdf_hash

            name = settings.robot_model
            desc = desc_in_bag or topic_desc
            if name in BUILTIN_MODELS and desc and urdf_hash(builtin_urdf(name)) != urdf_hash(desc):
                findings.append(f"built-in model '{name}' differs from the description in the "
                                "bag: the bag's description is used")
                locks = dict(BUILTIN_MODELS[name][1])
                locks.update(dict(settings.locked_joints))
                settings = replace(settings, robot_description=desc, robot_model="",
                                   locked_joints=tuple(locks.items()))
        elif desc_in_bag or topic_desc:
            # The URDF the node was using travels in the bag: it wins over file paths that may not
            # exist on this machine.
            settings = replace(settings, robot_description=desc_in_bag or topic_desc,
                               robot_description_file="", robot_model="")
        missing = ""
        if overrides_on and self.opts.limits:
            if not Path(self.opts.limits).is_file():
                raise AuditError(f"limits file {self.opts.limits} does not exist", code="no_limits")
            settings = replace(settings, limits_file=self.opts.limits)
            overrides["limits"] = self.opts.limits
        elif LIMITS_YAML_KEY in meta:  # the text the node's model was built from
            return settings, overrides, missing, recorded_limits(meta, settings.limits_file, findings)
        elif settings.limits_file and not Path(settings.limits_file).is_file():
            findings.append(f"the bag's limits_file {settings.limits_file} is not on this "
                            "machine: URDF limits used (pass --limits)")
            missing = settings.limits_file
            settings = replace(settings, limits_file="")
        elif settings.limits_file:
            findings.append(f"the bag does not record the limits file's text (older recorder): "
                            f"{settings.limits_file} as it is on this machine is used")
        return settings, overrides, missing, None

    def _resolve(self, meta: dict, topic_desc: str, *, first: bool,
                 since_ns: int | None = None) -> "Config":
        """The configuration of one metadata record, and how it differs from the node's."""
        from dyn_node.core.robot.model_source import build_model

        findings: list[str] = []
        settings, overrides, missing, limits = self._bag_settings(meta, topic_desc, findings,
                                                                  overrides_on=True)
        if not settings.has_model_source:
            raise AuditError("no robot model: the bag has no robot description (no dyn_node "
                             "metadata, no /robot_description); pass --robot-model or "
                             "--robot-description", code="no_model")
        try:
            model = build_model(settings, cache=self.opts.model_cache, limits_yaml=limits)
        except DynNodeError as exc:
            raise AuditError(f"robot model unusable: {exc}", code="no_model") from None
        differs: list[str] = []
        if missing and not overrides.get("limits"):
            differs.append(f"limits: the node read {missing}, which is not on this machine "
                           "(URDF limits used here)")
        if overrides:
            node_settings, _, node_missing, node_limits = self._bag_settings(
                meta, topic_desc, [], overrides_on=False)
            if node_settings.has_model_source and not node_missing:
                try:
                    differs += model_differences(build_model(
                        node_settings, cache=self.opts.model_cache, limits_yaml=node_limits), model)
                except DynNodeError as exc:
                    differs.append(f"the recorded model cannot be rebuilt here ({exc})")
        for f in findings:
            if f not in self.findings:
                self.findings.append(f)
        cfg = Config(settings, model, parameters_from_yaml(meta.get("parameters", "")), since_ns,
                      differs)
        if first:
            self.overrides = overrides
            desc_in_bag = meta.get("robot_description", "")
            if "robot_description" in overrides or "robot_model" in overrides:
                self.model_source = "override:" + ("robot_description" if "robot_description" in overrides
                                                   else "robot_model")
            elif settings.robot_description and settings.robot_description in (desc_in_bag, topic_desc):
                self.model_source = "bag:metadata" if settings.robot_description == desc_in_bag else "bag:topic"
            else:
                self.model_source = "bag:parameters"
            self.limits_source = limits_source(settings, overrides, limits is not None, missing)
        return cfg

    def _peek_description(self, reader: BagReader) -> BagMessage | None:
        for topic in ("/robot_description", "robot_description"):
            m = reader.peek_first(topic)
            if m is not None:
                return m
        return None


@dataclass
class AuditSource:
    """The bag and how its node was configured: the first configuration, then each change."""

    reader: BagReader
    configurations: list[Config]
    overrides: dict[str, Any]
    model_source: str
    bag_metadata_version: Any
    findings: list[str]  # shared with the later stages, which append theirs
    limits_source: str = ""  # where the first configuration's limits came from (limits_source)

    @property
    def first(self) -> Config:
        return self.configurations[0]


def open_bag(bag: str) -> BagReader:
    """A streaming reader of the bag; AuditError when none of its files is an MCAP file."""
    reader = BagReader(bag, topics=None)
    bad = []
    for f in reader.files:
        with open(f, "rb") as fh:
            if fh.read(8) != b"\x89MCAP0\r\n":
                bad.append(f.name)
    if len(bad) == len(reader.files):
        raise AuditError(f"bag {bag} is unreadable: {', '.join(bad)} is not an MCAP file",
                         code="bag_unreadable")
    return reader


def _effective_ns(meta: dict) -> int | None:
    """The log time from which a ``dyn_node`` metadata record applies (None: not recorded)."""
    try:
        return int(meta["effective_log_time_ns"])
    except (KeyError, ValueError, TypeError):
        return None
