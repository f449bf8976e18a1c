"""The strict YAML / JSON loader: an integer written with more digits than Python converts
(4,300) is one error naming its field and line, in both formats, not a traceback; shorter ones
are read exactly (each field then refuses what it cannot hold)."""
from __future__ import annotations

import pytest

from dyn_node.io.safe_load import MAX_INT_DIGITS, LoadError, load_json, load_yaml

HUGE = "9" * 4301


@pytest.mark.parametrize("text, field, line", [
    (f"points:\n- positions: [1.0, {HUGE}]\n", "points[0].positions[1]", 2),
    (f"a:\n  b: {{sec: -{HUGE}}}\n", "a.b.sec", 2),
    (f"x: !!int {HUGE}\n", "x", 1),
    ("x: 0x" + "f" * 5000 + "\n", "x", 1),   # int() has no limit for hex: refused all the same
    (f"- {HUGE}\n", "[0]", 1),
])
def test_a_huge_yaml_integer_names_its_field(text, field, line):
    with pytest.raises(LoadError) as e:
        load_yaml(text)
    assert (e.value.field, e.value.line) == (field, line)
    assert e.value.problem.startswith("too large for a number (an integer of ")
    assert e.value.problem.endswith(f" digits; at most {MAX_INT_DIGITS})") and MAX_INT_DIGITS == 4300
    assert "\n" not in str(e.value)


def test_a_huge_yaml_key_is_named_as_a_key():
    with pytest.raises(LoadError) as e:
        load_yaml(f"a: {{{HUGE}: 1}}\n")
    assert e.value.field == "a's keys"


@pytest.mark.parametrize("text, field", [
    ('{"points": [{"time_from_start": {"sec": %s}}]}' % HUGE, "points[0].time_from_start.sec"),
    ('{"a": [1, 2, -%s]}' % HUGE, "a[2]"),
    (HUGE, "the document"),
])
def test_a_huge_json_integer_names_its_field(text, field):
    with pytest.raises(LoadError) as e:
        load_json(text)
    assert e.value.field == field and e.value.problem == "too large for a number (an integer of 4301 digits; at most 4300)"


def test_integers_up_to_the_bound_are_read_exactly():
    d = "7" * MAX_INT_DIGITS
    n = int(d)
    assert load_yaml(f"a: {d}\nb: -{d}\n") == {"a": n, "b": -n}
    assert load_json(f'[{d}, -{d}, 1.5]') == [n, -n, 1.5]
    # a long float is not an integer: read as float() reads it
    assert load_json("[" + "1" * 5000 + ".0]") == [float("1" * 5000 + ".0")]
    with pytest.raises(LoadError):
        load_yaml(f"a: {d}7\n")
    with pytest.raises(LoadError):
        load_json(f"[-{d}7]")
