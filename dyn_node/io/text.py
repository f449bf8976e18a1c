"""What error messages echo of user input: capped in length and with control, format (NUL,
right-to-left override ...) and other unprintable characters escaped, so one bad value can
neither flood a terminal nor reorder what it shows."""
from __future__ import annotations

import reprlib
from typing import Any, Iterable

#: Characters of one echoed value (a string, a number) at most.
VALUE_CHARS = 60
#: Names listed at most (the rest counted).
NAMES_SHOWN = 10

_REPR = reprlib.Repr()
_REPR.maxstring = VALUE_CHARS
_REPR.maxother = VALUE_CHARS
_REPR.maxlong = 40
_REPR.maxlevel = 3
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = 6
_REPR.maxdict = 4


def escape(text: str, limit: int = VALUE_CHARS) -> str:
    """``text`` cut to ``limit`` characters (saying how many more there were), each character
    Python would not print as itself (str.isprintable) written as its escape."""
    s = str(text)
    more = len(s) - limit
    s = s[:limit] if more > 0 else s
    out = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in s)
    return out + (f"…(+{more} chars)" if more > 0 else "")


def shown(value: Any) -> str:
    """A bounded, escaped ``repr`` of a value from a file: strings, numbers, nested lists."""
    try:
        return _REPR.repr(value)
    except ValueError:
        # int → str refuses more than sys.get_int_max_str_digits() digits
        return f"<an integer of {value.bit_length()} bits>" if isinstance(value, int) \
            else f"<{type(value).__name__}>"


def name_list(names: Iterable[Any], limit: int = NAMES_SHOWN) -> str:
    """``a, b, c`` of the first ``limit`` names (each escaped), then how many more."""
    names = list(names)
    head = ", ".join(escape(str(n)) for n in names[:limit])
    return head + (f" … and {len(names) - limit} more" if len(names) > limit else "")


__all__ = ["NAMES_SHOWN", "VALUE_CHARS", "escape", "name_list", "shown"]
