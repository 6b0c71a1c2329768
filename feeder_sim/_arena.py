"""Scratch memory for the compiled step: arrays carved out of one preallocated buffer.

A ``time_stepping`` step of a single part needs some 150 temporary arrays (contacts, rows,
islands, the Dantzig pivots' systems). Each ``np.empty`` in numba costs a ``malloc``, a
``free`` and the atomic reference-count updates of every hand-over of the array, which
together took about 80 % of such a step. An arena hands out arrays from a buffer sized once
instead: an allocation is a bump of an offset, the arrays carry no reference count (numba
skips counting for arrays without an owner), and the whole step's scratch is released at
once by resetting the offset.

Kernels see an arena as its ``state`` alone, an int64 array (:data:`BASE` address of the
buffer, :data:`CAPACITY`, :data:`USED`, :data:`SHORT`, :data:`PEAK`, in bytes), and the
allocators are inlined where they are called (a call of a numba function costs some 20 ns of
argument and reference handling, more than a bump of an offset).

Rules that keep that safe:

* An arena array is valid until its arena is released below it (:func:`release` to an
  earlier :func:`mark`, or the next step's reset). Nothing that outlives that may point into
  it: results a kernel returns to Python are copied out, or come from an arena of capacity
  0 (:func:`heap_state` from Python, :func:`heap_arena` in a kernel), whose arrays are all
  ordinary numpy ones.
* A request the buffer cannot hold is served from the heap and counted (``SHORT`` bytes): the
  step stays correct and the owner grows the buffer before the next call
  (:func:`grown_capacity`).
* The buffer belongs to the Python object holding the :class:`Arena`, which must outlive the
  kernel call. One arena belongs to one stepper; kernels release the GIL, so two threads
  never share one.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
from numba import types
from numba.extending import intrinsic, register_jitable
import numpy as np

from feeder_sim._jit import inner

BASE, CAPACITY, USED, SHORT, PEAK = range(5)

# The allocators are generic functions (``register_jitable``), not dispatchers: numba types
# them with the plain types of their arguments (a dispatcher is compiled again for every
# literal it meets: a size of 0, a column count of 3), and LLVM inlines them where they are
# called (a call of a numba function costs some 20 ns of argument and reference handling).
_allocator = register_jitable(forceinline=True)
_ALIGN = 64     # bytes; a cache line, so that no two arrays share one


class Arena(NamedTuple):
    """A scratch buffer and the state kernels allocate from (see the module docstring)."""

    buf: np.ndarray     # (capacity,) uint8, owned here
    state: np.ndarray   # (5,) int64


def new_arena(capacity_bytes: int) -> Arena:
    """An empty arena of ``capacity_bytes``."""
    buf = np.zeros(max(int(capacity_bytes), _ALIGN), np.uint8)
    return Arena(buf, np.array([buf.ctypes.data, buf.shape[0], 0, 0, 0], np.int64))


def grown_capacity(arena: Arena) -> int:
    """The capacity an arena that fell short should have: twice its peak demand (bytes)."""
    state = arena.state
    return int(2 * max(state[CAPACITY], state[PEAK] + state[SHORT]))


@intrinsic
def _address(typingctx, address, dtype):
    """The integer ``address`` as a typed pointer."""
    item = dtype.instance_type if isinstance(dtype, types.NumberClass) else dtype.dtype
    sig = types.CPointer(item)(address, dtype)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(item)))

    return sig, codegen


@intrinsic
def borrow(typingctx, x):
    """``x`` as a view no kernel owns: the same data, shape and strides without its owner
    (meminfo), so that handing it on costs no reference counting. numba counts references
    with atomic updates, two per array per non-inlined call, which took a third of a small
    step's time for the arrays it was given. Valid while the caller holds ``x``."""
    sig = x(x)

    def codegen(context, builder, signature, args):
        view = context.make_array(signature.args[0])(context, builder, value=args[0])
        view.meminfo = context.get_constant_null(types.MemInfoPointer(types.voidptr))
        view.parent = context.get_constant_null(types.pyobject)
        return view._getvalue()

    return sig, codegen


@inner
def heap_arena():
    """An arena state of capacity 0: every array it gives is an ordinary (heap) numpy array."""
    return np.zeros(5, np.int64)


@inner
def local_arena(buf):
    """An arena state over ``buf`` (uint8), for a kernel that makes its scratch in one
    allocation: ``buf`` must stay in use until the last array carved from it is (numba frees
    an array after its last use), and results must be copied out before it goes."""
    state = np.zeros(5, np.int64)
    state[BASE] = buf.ctypes.data
    state[CAPACITY] = buf.shape[0]
    return state


@_allocator
def mark(ar) -> int:
    """The arena's level now, for :func:`release`."""
    return ar[USED]


@_allocator
def release(ar, level: int) -> None:
    """Give back everything handed out since ``mark`` returned ``level``."""
    if ar[USED] > ar[PEAK]:
        ar[PEAK] = ar[USED]
    ar[USED] = level


@_allocator
def _reserve(ar, nbytes):
    """Offset of ``nbytes`` fresh bytes, or -1 (counted) when the buffer cannot hold them."""
    start = (ar[USED] + (_ALIGN - 1)) & -_ALIGN
    end = start + nbytes
    if end > ar[CAPACITY]:
        if ar[CAPACITY]:
            ar[SHORT] += nbytes
        return -1
    ar[USED] = end
    return start


# The heap fallbacks are calls of their own: a cold path, kept out of every inlined site.
@inner
def _heap_f(n):
    return np.empty(n)


@inner
def _heap_f2(n, m):
    return np.empty((n, m))


@inner
def _heap_i(n):
    return np.empty(n, np.int64)


@inner
def _heap_i2(n, m):
    return np.empty((n, m), np.int64)


@inner
def _heap_b(n):
    return np.empty(n, np.bool_)


@inner
def _heap_like(like, n):
    return np.empty(n, like.dtype)


@_allocator
def empty_f(ar, n):
    """``np.empty(n)``."""
    at = _reserve(ar, 8 * n)
    if at < 0:
        return _heap_f(n)
    return numba.carray(_address(ar[BASE] + at, numba.float64), (n,))


@_allocator
def empty_f2(ar, n, m):
    """``np.empty((n, m))``."""
    at = _reserve(ar, 8 * n * m)
    if at < 0:
        return _heap_f2(n, m)
    return numba.carray(_address(ar[BASE] + at, numba.float64), (n, m))


@_allocator
def empty_i(ar, n):
    """``np.empty(n, np.int64)``."""
    at = _reserve(ar, 8 * n)
    if at < 0:
        return _heap_i(n)
    return numba.carray(_address(ar[BASE] + at, numba.int64), (n,))


@_allocator
def empty_b(ar, n):
    """``np.empty(n, np.bool_)``."""
    at = _reserve(ar, n)
    if at < 0:
        return _heap_b(n)
    return numba.carray(_address(ar[BASE] + at, numba.boolean), (n,))


@_allocator
def zeros_f(ar, n):
    """``np.zeros(n)``."""
    x = empty_f(ar, n)
    for i in range(n):
        x[i] = 0.0
    return x


@_allocator
def zeros_f2(ar, n, m):
    """``np.zeros((n, m))``."""
    x = empty_f2(ar, n, m)
    for i in range(n):
        for j in range(m):
            x[i, j] = 0.0
    return x


@_allocator
def full_i(ar, n, value):
    """``np.full(n, value, np.int64)``."""
    x = empty_i(ar, n)
    for i in range(n):
        x[i] = value
    return x


@_allocator
def arange_i(ar, n):
    """``np.arange(n)``."""
    x = empty_i(ar, n)
    for i in range(n):
        x[i] = i
    return x


@_allocator
def full_b(ar, n, value):
    """``np.full(n, value, np.bool_)``."""
    x = empty_b(ar, n)
    for i in range(n):
        x[i] = value
    return x


@_allocator
def copy_f(ar, src):
    """``src.copy()`` of a 1-d float array."""
    x = empty_f(ar, src.shape[0])
    for i in range(src.shape[0]):
        x[i] = src[i]
    return x


@_allocator
def copy_f2(ar, src):
    """``src.copy()`` of a 2-d float array."""
    n, m = src.shape
    x = empty_f2(ar, n, m)
    for i in range(n):
        for j in range(m):
            x[i, j] = src[i, j]
    return x


@_allocator
def copy_i(ar, src):
    """``src.copy()`` of a 1-d int array."""
    x = empty_i(ar, src.shape[0])
    for i in range(src.shape[0]):
        x[i] = src[i]
    return x


@_allocator
def full_i2(ar, n, m, value):
    """``np.full((n, m), value, np.int64)``."""
    at = _reserve(ar, 8 * n * m)
    if at < 0:
        x = _heap_i2(n, m)
    else:
        x = numba.carray(_address(ar[BASE] + at, numba.int64), (n, m))
    for i in range(n):
        for j in range(m):
            x[i, j] = value
    return x


@_allocator
def empty_like(ar, like, n):
    """``np.empty(n, like.dtype)`` (``like`` a 1-d array)."""
    at = _reserve(ar, like.itemsize * n)
    if at < 0:
        return _heap_like(like, n)
    return numba.carray(_address(ar[BASE] + at, like), (n,))


@_allocator
def gather(ar, src, idx):
    """``src[idx]`` of a 1-d array."""
    x = empty_like(ar, src, idx.shape[0])
    for q in range(idx.shape[0]):
        x[q] = src[idx[q]]
    return x


@_allocator
def gather_rows(ar, src, idx):
    """``src[idx]`` of an (n, 2) float array."""
    x = empty_f2(ar, idx.shape[0], 2)
    for q in range(idx.shape[0]):
        x[q, 0] = src[idx[q], 0]
        x[q, 1] = src[idx[q], 1]
    return x


@_allocator
def concat(ar, x, y):
    """``np.concatenate((x, y))`` of two 1-d arrays of one dtype."""
    n = x.shape[0]
    out = empty_like(ar, x, n + y.shape[0])
    for q in range(n):
        out[q] = x[q]
    for q in range(y.shape[0]):
        out[n + q] = y[q]
    return out


def heap_state() -> np.ndarray:
    """An arena state of capacity 0, for kernels called from Python: every array they make is
    an ordinary numpy array that may outlive the call."""
    return np.zeros(5, np.int64)
