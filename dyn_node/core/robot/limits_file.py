"""The limits file as bytes on disk: read once as UTF-8 text, and its sha256. The model is built
from this text and the bag records it, so the recorded hash is the file's bytes' hash (no
newline translation between the read and the record). No numpy: the bag writer imports it."""
from __future__ import annotations

import hashlib
from pathlib import Path

from dyn_node.errors import ModelError
from dyn_node.io.files import FileProblem, read_bytes

#: Largest limits file read (bytes): real ones are a few kB.
MAX_LIMITS_BYTES = 16 * 1024 * 1024


def read_limits_file(path: str | Path) -> str:
    """The limits file's text: its bytes decoded as UTF-8, newlines untouched. Raises
    ModelError (``limits_file_missing``, or ``limits_bad_yaml`` for bytes that are not UTF-8)."""
    p = Path(path)
    if not p.exists():
        raise ModelError(f"limits file {p} does not exist", code="limits_file_missing")
    try:
        data = read_bytes(p, max_bytes=MAX_LIMITS_BYTES)
    except FileProblem as exc:
        raise ModelError(f"limits file {p} {exc}", code="limits_file_missing") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ModelError(f"{p}: not UTF-8 text: {exc}", code="limits_bad_yaml") from exc


def limits_sha256(data: str | bytes) -> str:
    """The sha256 (hex) of a limits file's bytes, or of a limits text's UTF-8 bytes (the same
    digest for the text :func:`read_limits_file` returns)."""
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    return hashlib.sha256(raw).hexdigest()


__all__ = ["limits_sha256", "read_limits_file"]
