"""A map of an earlier Taichi runtime that Python collects late (after a reassignment, or by
the cycle collector at any moment) must not touch the running runtime.

Two ways it did in taichi 1.7.4, each a crash at some later kernel: a collected argument pack
asks the *running* program to delete the pack's C++ address, which can be the running map's own
pack; and a map that kept its SNode tree kept the earlier program alive, whose destruction then
unmapped memory under the running runtime. The spy below stands in for the running program's
`delete_argpack` and records every address it is asked to delete, so the tests fail on the
cause itself, whether or not the addresses happen to collide this time.
"""

from __future__ import annotations

import gc
import weakref

import numpy as np
from helpers import BUILDING, fresh_runtime, pose, scan_from_world, small_config
from taichi.lang import impl

from tisem.mapper import Mapper


class DeleteSpy:
    """The running program, except that `delete_argpack` records what it is asked to delete
    and forwards only the no-op (None)."""

    def __init__(self, prog):
        self._prog = prog
        self.deleted: list = []

    def delete_argpack(self, address):
        if address is not None:
            self.deleted.append(address)
            return None  # (forwarding it is the very crash this test is about)
        return self._prog.delete_argpack(address)

    def __getattr__(self, name):
        return getattr(self._prog, name)


def one_wall_scan(stamp: float, index: int):
    wall = np.column_stack([np.full(50, 6.1), np.linspace(-2, 2, 50), np.full(50, 0.3)])
    return scan_from_world(wall, pose(), stamp, labels=np.full(50, BUILDING), index=index)


def test_a_map_of_an_earlier_runtime_collected_late_deletes_nothing_of_the_running_one(
    taichi_cpu,
):
    old = Mapper(small_config())
    old.integrate(one_wall_scan(0.0, 0))
    fresh_runtime()
    mapper = Mapper(small_config())
    runtime = impl.get_runtime()
    spy = DeleteSpy(runtime.prog)
    runtime.prog = spy
    try:
        del old
        gc.collect()
    finally:
        runtime.prog = spy._prog
    assert spy.deleted == [], "a pack of the earlier runtime was deleted in the running one"
    # and the running map works
    mapper.integrate(one_wall_scan(0.0, 0))
    labels, _ = mapper.query(np.array([[6.1, 0.0, 0.3]]))
    assert labels.tolist() == [BUILDING]


def test_a_map_kept_past_a_new_runtime_keeps_no_earlier_program_alive(taichi_cpu):
    """The earlier runtime's program goes with its runtime, not when Python collects a map of
    it: destroyed later, it unmaps memory while the running runtime may have been given the
    same addresses (a crash at some later kernel)."""
    old = Mapper(small_config())
    old.integrate(one_wall_scan(0.0, 0))
    program = weakref.ref(impl.get_runtime().prog)
    fresh_runtime()
    assert program() is None, "the earlier runtime's program outlived it"
    mapper = Mapper(small_config())
    del old
    gc.collect()
    mapper.integrate(one_wall_scan(0.0, 0))
    labels, _ = mapper.query(np.array([[6.1, 0.0, 0.3]]))
    assert labels.tolist() == [BUILDING]
