"""Open dyn_node bags, service events included, in the two Python readers people reach for.

rosbags 0.11 registers a service type ``pkg/srv/X_Event`` as ``pkg/srv/msg/X_Event`` (and its
request and response as ``pkg/msg/X_Request``), so ``AnyReader.deserialize`` cannot decode a
service event; mcap_ros2 0.6 refuses any type name with ``_`` in it. Every other message decodes
in both as they are. docs/recording.md shows the lines a user writes::

    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        typestore = rosbags_typestore(reader)
        msgs = [typestore.deserialize_cdr(raw, c.msgtype) for c, _t, raw in reader.messages()]

    reader = make_reader(open(path, "rb"), decoder_factories=[mcap_decoder_factory()])
"""
from __future__ import annotations

import re
from typing import Any

# pkg/srv/X_Request, pkg/X_Request (how our schemas name an event's fields), pkg/srv/msg/X_Event
_SRV_REF = re.compile(r"\b([A-Za-z][A-Za-z0-9_]*)/(?:srv/)?(?:msg/)?([A-Z][A-Za-z0-9]*)_(Request|Response|Event)\b")


def _srv_name(name: str) -> str | None:
    """``pkg/srv/X_Part`` for any spelling rosbags gives a service part, else None."""
    m = _SRV_REF.fullmatch(name)
    return f"{m.group(1)}/srv/{m.group(2)}_{m.group(3)}" if m else None


def _renamed(tree: Any, names: dict[str, str]) -> Any:
    """A rosbags field tree with every type name in ``names`` replaced."""
    if isinstance(tree, str):
        return names.get(tree, tree)
    if isinstance(tree, tuple):
        return tuple(_renamed(x, names) for x in tree)
    if isinstance(tree, list):
        return [_renamed(x, names) for x in tree]
    return tree


def service_types(definition: str, msgtype: str) -> dict[str, Any]:
    """rosbags types (name -> parse tree) of one ``ros2msg`` definition, with the service parts
    (``pkg/srv/X_Request|_Response|_Event``) under the names ROS gives them."""
    from rosbags.typesys import get_types_from_msg

    types = get_types_from_msg(definition, msgtype)
    names = {k: s for k in types if (s := _srv_name(k)) is not None and s != k}
    return {names.get(k, k): _renamed(v, names) for k, v in types.items()}


def rosbags_typestore(reader: Any = None) -> Any:
    """A rosbags Jazzy typestore holding every type ``reader`` (an open ``AnyReader``) found in
    the bag, service events under their right names: ``typestore.deserialize_cdr(raw,
    connection.msgtype)`` then decodes every message, service events included."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for conn in getattr(reader, "connections", ()):
        if conn.msgdef.format == MessageDefinitionFormat.MSG and conn.msgdef.data:
            store.register(service_types(conn.msgdef.data, conn.msgtype))
    return store


def mcap_decoder_factory() -> Any:
    """An mcap_ros2 ``DecoderFactory`` that also decodes ``pkg/srv/X_Event`` schemas (their
    type names renamed without ``_``: CDR carries no names, so the bytes decode the same)."""
    from mcap.well_known import MessageEncoding, SchemaEncoding
    from mcap_ros2._dynamic import generate_dynamic
    from mcap_ros2.decoder import DecoderFactory

    class _Factory(DecoderFactory):
        def decoder_for(self, message_encoding: str, schema: Any):
            if (schema is None or message_encoding != MessageEncoding.CDR
                    or schema.encoding != SchemaEncoding.ROS2 or _srv_name(schema.name) is None):
                return super().decoder_for(message_encoding, schema)
            decoder = self._decoders.get(schema.id)
            if decoder is None:
                name = _SRV_REF.sub(r"\1/\2\3", schema.name)
                decoder = generate_dynamic(name, _SRV_REF.sub(r"\1/\2\3", schema.data.decode()))[name]
                self._decoders[schema.id] = decoder
            return decoder

    return _Factory()
