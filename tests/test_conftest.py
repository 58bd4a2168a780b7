"""The test session's own machinery (tests/conftest.py), where it changes how the suite ends."""

from __future__ import annotations

import gc

from conftest import settle_heap


class _Cycle:
    """Garbage only a full collection frees: a reference cycle, with a ``__del__`` that records it."""

    freed: list[str] = []

    def __init__(self, name: str):
        self.name, self.me = name, self

    def __del__(self):
        _Cycle.freed.append(self.name)


def test_a_worker_s_heap_is_collected_then_frozen_so_pytest_s_last_collections_skip_it():
    """An xdist worker's teardown (settle_heap) frees the garbage its tests left, then leaves the survivors to
    gc.freeze, so that pytest's five collections after the worker's report do not walk them again."""
    _Cycle.freed.clear()
    gc.disable()  # no automatic collection before settle_heap's
    try:
        kept = _Cycle("kept")
        _Cycle("garbage")
        assert gc.get_freeze_count() == 0
        settle_heap()
        assert _Cycle.freed == ["garbage"]  # collected (its __del__ ran), not frozen with the living
        assert gc.get_freeze_count() > 0 and kept.name == "kept"
    finally:
        gc.unfreeze()
        gc.enable()
