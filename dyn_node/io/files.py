"""A user's file read as text: only a regular file (a FIFO would block, a symlink to /dev/zero
never end), of bounded size, as UTF-8 (a leading byte-order mark dropped)."""
from __future__ import annotations

import os
import stat
from pathlib import Path

#: Largest trajectory or limits file read (bytes): a 1,000,000-point JSON trajectory of a
#: 7-joint arm is about 200 MB.
MAX_FILE_BYTES = 512 * 1024 * 1024


class FileProblem(ValueError):
    """The file cannot be read as text; ``str()`` says why (without the path)."""


def read_bytes(path: str | Path, *, max_bytes: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed); raises :class:`FileProblem`."""
    try:
        # O_NONBLOCK: opening a FIFO for reading must not wait for a writer
        fd = os.open(os.fspath(path), os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise FileProblem(f"cannot be read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a file")
            raise FileProblem(f"is {kind}, not a regular file")
        if st.st_size > max_bytes:
            raise FileProblem(f"is {st.st_size} bytes, more than the {max_bytes} read at most")
        with os.fdopen(fd, "rb", closefd=True) as f:
            fd = -1
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise FileProblem(f"cannot be read: {exc.strerror or exc}") from None
    finally:
        if fd >= 0:
            os.close(fd)
    if len(data) > max_bytes:  # it grew while read
        raise FileProblem(f"is more than the {max_bytes} bytes read at most")
    return data


def read_text(path: str | Path, *, max_bytes: int = MAX_FILE_BYTES) -> str:
    """:func:`read_bytes` decoded as UTF-8, a leading byte-order mark dropped."""
    try:
        return read_bytes(path, max_bytes=max_bytes).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FileProblem(f"not UTF-8 text: {exc.reason} at byte {exc.start}") from None


__all__ = ["FileProblem", "MAX_FILE_BYTES", "read_bytes", "read_text"]
