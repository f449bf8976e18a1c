"""conftest's ``DYN_TEST_SHUFFLE``: a seeded order, the same for the same seed, every test once,
each module's tests together (its module-scoped fixtures set up once)."""
from __future__ import annotations

from dataclasses import dataclass

from conftest import shuffled


@dataclass(frozen=True)
class Item:
    nodeid: str


ITEMS = [Item(f"test/test_{m}.py::test_{t}") for m in "abcdef" for t in range(8)]


def test_a_seed_gives_one_order_with_every_test_once():
    a, b = shuffled(list(ITEMS), "7"), shuffled(list(ITEMS), "7")
    assert a == b and sorted(a, key=ITEMS.index) == ITEMS
    assert a != ITEMS and shuffled(list(ITEMS), "8") != a


def test_modules_and_their_tests_are_shuffled_but_stay_together():
    order = shuffled(list(ITEMS), "7")
    modules = [i.nodeid.split("::")[0] for i in order]
    runs = [m for k, m in enumerate(modules) if k == 0 or modules[k - 1] != m]
    assert len(runs) == 6 and runs != sorted(runs)   # each module once, not in file order
    first = [i for i in order if i.nodeid.startswith("test/test_a.py")]
    assert first != [i for i in ITEMS if i.nodeid.startswith("test/test_a.py")]
