"""The compiled step's scratch (``feeder_sim.compiled.arena``): what an arena hands out, where it
falls short, and what it gives back."""

from __future__ import annotations

import numba
import numpy as np

from feeder_sim.compiled.arena import (
    BLOCKS,
    borrow,
    empty_f,
    empty_i2,
    heap_state,
    mark,
    N_BLOCKS,
    new_arena,
    PEAK,
    release,
    SHORT,
    USED,
)


@numba.njit
def _fill_past_the_end(state, sizes):
    """Allocate arrays of ``sizes`` (float64 counts) after a mark, write each with its index
    and check them all; then release to the mark. Returns (sum of the check, blocks and
    bytes used at the deepest point, blocks and bytes after the release)."""
    ar = borrow(state)
    level = mark(ar)
    total = 0.0
    arrays = []
    for k in range(sizes.shape[0]):
        x = empty_f(ar, sizes[k])
        for i in range(sizes[k]):
            x[i] = k
        arrays.append(x)
    grid = empty_i2(ar, 3, 4)
    for i in range(3):
        for j in range(4):
            grid[i, j] = 10 * i + j
    for k in range(len(arrays)):
        for i in range(arrays[k].shape[0]):
            total += arrays[k][i] - k       # 0 unless a later array overwrote this one
    total += grid.sum() - 138
    deepest = (ar[N_BLOCKS], ar[USED])
    release(ar, level)
    return total, deepest, (ar[N_BLOCKS], ar[USED])


def test_an_arena_serves_what_it_cannot_hold_from_blocks_it_frees_at_the_mark():
    # 64 bytes hold one array of 8 floats (and the empty one after it): the rest (8 arrays,
    # 1 700 floats, the 3 x 4 ints) comes from overflow blocks, one each, none overlapping
    # another; released to the mark taken before them, the arena is back where it was, the
    # blocks freed, their bytes counted.
    arena = new_arena(64)
    sizes = np.array([8, 100, 1, 0, 200, 300, 400, 300, 200, 199], np.int64)
    total, deepest, after = _fill_past_the_end(arena.state, sizes)
    assert total == 0.0
    assert deepest == (9, 64)
    assert after == (0, 0)
    assert arena.state[BLOCKS] == 0
    assert arena.state[SHORT] == 8 * (sizes[1:].sum()) + 8 * 12
    assert arena.state[PEAK] == 64

    # a roomy arena: everything in the buffer, 64-byte aligned, nothing counted short
    roomy = new_arena(1 << 16)
    total, deepest, after = _fill_past_the_end(roomy.state, sizes)
    assert total == 0.0 and deepest[0] == 0 and after == (0, 0)
    assert roomy.state[SHORT] == 0
    used = 0
    for nbytes in [8 * int(n) for n in sizes] + [8 * 12]:
        used = -(-used // 64) * 64 + nbytes        # each array starts on a cache line
    assert deepest[1] == used


def test_a_release_keeps_the_blocks_taken_before_its_mark():
    # blocks linked before a mark survive a release to it; a release to 0 frees them all
    @numba.njit
    def nested(state):
        ar = borrow(state)
        outer = empty_f(ar, 50)             # a block (the buffer holds 8 floats)
        for i in range(50):
            outer[i] = 1.5
        level = mark(ar)
        inner = empty_f(ar, 70)
        inner[:] = -1.0
        n_inner = ar[N_BLOCKS]
        release(ar, level)
        kept = ar[N_BLOCKS]
        again = empty_f(ar, 70)             # may reuse the freed block's memory
        again[:] = 2.0
        ok = outer.sum() == 75.0
        release(ar, 0)
        return n_inner, kept, ok, ar[N_BLOCKS], ar[BLOCKS]

    assert nested(new_arena(64).state) == (2, 1, True, 0, 0)


def test_a_heap_state_gives_arrays_that_outlive_the_call():
    @numba.njit
    def make(state, n):
        x = empty_f(state, n)
        for i in range(n):
            x[i] = i
        return x

    out = [make(heap_state(), 1000) for _ in range(3)]
    assert all(np.array_equal(x, np.arange(1000.0)) for x in out)
    assert all(x.flags.owndata or x.base is not None for x in out)
