"""Scratch memory for the compiled step: arrays carved out of one preallocated buffer.

A ``time_stepping`` step of a single part needs some 150 temporary arrays (contacts, rows,
islands, the Dantzig pivots' systems). Each ``np.empty`` in numba costs a ``malloc``, a
``free`` and the atomic reference-count updates of every hand-over of the array, which
together took about 80 % of such a step. An arena hands out arrays from a buffer sized once
instead: an allocation is a bump of an offset, the arrays carry no reference count (numba
skips counting for arrays without an owner), and the whole step's scratch is released at
once by resetting the offset.

Kernels see an arena as its ``state`` alone, an int64 array (:data:`BASE` address of the
buffer, :data:`CAPACITY`, :data:`USED`, :data:`SHORT`, :data:`PEAK`, in bytes;
:data:`BLOCKS`, :data:`N_BLOCKS`: the overflow blocks, below), and the allocators are
inlined where they are called (a call of a numba function costs some 20 ns of argument and
reference handling, more than a bump of an offset).

An arena's arrays never have an owner, whatever happens: a request the buffer cannot hold is
served from a block of its own (``malloc``), linked to the arena and freed when the arena is
released below it; the bytes are counted (``SHORT``) and the owner grows the buffer before
the next call (:func:`grown_capacity`). numba then knows at compile time that the step's
scratch arrays have no owner and leaves out their reference counting: while a short buffer
fell back to ordinary numpy arrays instead, the step's machine code kept 4 452 counting
sites (865 now, for what the kernels it calls return) and a one-part step took 1.8 times
as long.

Kernels called from Python get a *heap state* instead (:func:`heap_state`, :func:`heap_arena`:
an int32 array, told apart from an arena by its type when a kernel is compiled): every array
made from it is an ordinary numpy array that may outlive the call.

Rules that keep that safe:

* An arena array is valid until its arena is released below it (:func:`release` to an
  earlier :func:`mark`, or the next step's reset). Nothing that outlives that may point into
  it: results a kernel returns to Python are copied out, and the arena is released to 0 (its
  blocks freed) before it is dropped.
* The buffer belongs to the Python object holding the :class:`Arena`, which must outlive the
  kernel call. One arena belongs to one stepper; kernels release the GIL, so two threads
  never share one.
"""

from __future__ import annotations

from collections.abc import Callable
import inspect
from typing import NamedTuple

import numba
from numba import types
from numba.extending import intrinsic, overload, register_jitable
import numpy as np

from feeder_sim.compiled.jit import inner

BASE, CAPACITY, USED, SHORT, PEAK, BLOCKS, N_BLOCKS = range(7)
_FIELDS = N_BLOCKS + 1
HEAP_DTYPE = np.int32       # a heap state's dtype; an arena's state is int64

# The allocators are generic functions (``register_jitable``, ``overload``), not dispatchers:
# numba types them with the plain types of their arguments (a dispatcher is compiled again
# for every literal it meets: a size of 0, a column count of 3), and LLVM inlines them where
# they are called (a call of a numba function costs some 20 ns of argument and reference
# handling).
_INLINE = {'forceinline': True}
_allocator = register_jitable(**_INLINE)
_ALIGN = 64     # bytes; a cache line, so that no two arrays share one
_BLOCK_HEADER = 16      # bytes before an overflow block's arrays: the next block's address
# a mark holds the arena's offset and, above this bit, its count of overflow blocks
_MARK_SHIFT = 44


class Arena(NamedTuple):
    """A scratch buffer and the state kernels allocate from (see the module docstring)."""

    buf: np.ndarray     # (capacity,) uint8, owned here
    state: np.ndarray   # (_FIELDS,) int64


@register_jitable
def _arena_state(address: int, capacity_bytes: int) -> np.ndarray:
    """The state of an empty arena over the buffer at ``address`` (from Python or a kernel)."""
    state = np.zeros(_FIELDS, np.int64)
    state[BASE] = address
    state[CAPACITY] = capacity_bytes
    return state


def new_arena(capacity_bytes: int) -> Arena:
    """An empty arena of ``capacity_bytes``."""
    buf = np.zeros(max(int(capacity_bytes), _ALIGN), np.uint8)
    return Arena(buf, _arena_state(buf.ctypes.data, buf.shape[0]))


def grown_capacity(arena: Arena) -> int:
    """The capacity an arena that fell short should have: twice its peak demand (bytes)."""
    state = arena.state
    return int(2 * max(state[CAPACITY], state[PEAK] + state[SHORT]))


def heap_state() -> np.ndarray:
    """A heap state, for kernels called from Python: every array they make is an ordinary
    numpy array that may outlive the call. It holds nothing: its type is what kernels read."""
    return np.zeros(0, HEAP_DTYPE)


def _is_heap(ar) -> bool:
    return isinstance(ar, types.Array) and ar.dtype == numba.from_dtype(HEAP_DTYPE)


@intrinsic
def _address(typingctx, address, dtype):
    """The integer ``address`` as a typed pointer."""
    item = dtype.instance_type if isinstance(dtype, types.NumberClass) else dtype.dtype
    sig = types.CPointer(item)(address, dtype)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(item)))

    return sig, codegen


@intrinsic
def _malloc(typingctx, nbytes):
    """The address of ``nbytes`` fresh bytes from numba's allocator, 0 where the system has
    none left: then :func:`_overflow`'s first write (to address 0) ends the process.

    Neither a raise nor a test here: a MemoryError that can come from every allocation of a
    step gives each one an exit that numba cleans up after, and even a trap on a null block
    kept most of the reference counting that arrays without owners save (measured: 1 584
    and 1 707 decrements left in the step's machine code instead of 626; a one-part step
    1.15 times as long with the MemoryError)."""
    def codegen(context, builder, signature, args):
        return builder.ptrtoint(context.nrt.allocate_unchecked(builder, args[0]),
                                context.get_value_type(types.int64))

    return types.int64(types.intp), codegen


@intrinsic
def _free(typingctx, address):
    """Give back a block of :func:`_malloc`."""
    def codegen(context, builder, signature, args):
        context.nrt.free(builder, builder.inttoptr(args[0], context.get_value_type(
            types.voidptr)))
        return context.get_dummy_value()

    return types.none(types.int64), codegen


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
    """A heap state (:func:`heap_state`) made in a kernel."""
    return np.zeros(0, HEAP_DTYPE)


@inner
def local_arena(buf):
    """An arena state over ``buf`` (uint8), for a kernel that makes its scratch in one
    allocation: ``buf`` must stay in use until the last array carved from it is (numba frees
    an array after its last use), and results must be copied out, and the state released
    to 0, before it goes."""
    return _arena_state(buf.ctypes.data, buf.shape[0])


# The overflow path, a function of its own: LLVM inlines it where it likes, which costs
# code on a cold path but adds no exit (it cannot raise).
@inner
def _overflow(ar, nbytes):
    """The address of ``nbytes`` bytes in a new block linked to the arena (counted)."""
    block = _malloc(nbytes + _BLOCK_HEADER)
    numba.carray(_address(block, numba.int64), (1,))[0] = ar[BLOCKS]
    ar[BLOCKS] = block
    ar[N_BLOCKS] += 1
    ar[SHORT] += nbytes
    return block + _BLOCK_HEADER


@inner
def _free_blocks(ar, keep):
    """Free the overflow blocks linked after the first ``keep``."""
    while ar[N_BLOCKS] > keep:
        block = ar[BLOCKS]
        ar[BLOCKS] = numba.carray(_address(block, numba.int64), (1,))[0]
        ar[N_BLOCKS] -= 1
        _free(block)


@_allocator
def _reserve(ar, nbytes):
    """The address of ``nbytes`` fresh bytes: in the buffer, or in an overflow block."""
    start = (ar[USED] + (_ALIGN - 1)) & -_ALIGN
    end = start + nbytes
    if end > ar[CAPACITY]:
        return _overflow(ar, nbytes)
    ar[USED] = end
    return ar[BASE] + start


# The heap state's allocations are calls of their own, kept out of every inlined site.
@inner
def _heap_f(n):
    return np.empty(n)


@inner
def _heap_i(n):
    return np.empty(n, np.int64)


@inner
def _heap_b(n):
    return np.empty(n, np.bool_)


@inner
def _heap_like(like, n):
    return np.empty(n, like.dtype)


def _release_arena(ar, level):
    if ar[USED] > ar[PEAK]:
        ar[PEAK] = ar[USED]
    ar[USED] = level & ((1 << _MARK_SHIFT) - 1)
    if ar[N_BLOCKS] > level >> _MARK_SHIFT:
        _free_blocks(ar, level >> _MARK_SHIFT)


def _two_forms(on_heap: Callable, in_arena: Callable) -> Callable:
    """Make the decorated stub (its signature and docstring) a compiled-only function,
    inlined where it is called, that is ``on_heap`` for a heap state (:data:`HEAP_DTYPE`)
    and ``in_arena`` for an arena: the type of the state picks one when a kernel is
    compiled."""
    def register(stub: Callable) -> Callable:
        def typer(*args):
            return on_heap if _is_heap(args[0]) else in_arena

        # numba checks the forms' signatures against this one, annotations included
        stub_sig = inspect.signature(stub)
        typer.__signature__ = stub_sig.replace(
            parameters=[p.replace(annotation=p.empty) for p in stub_sig.parameters.values()],
            return_annotation=stub_sig.empty)
        overload(stub, jit_options=_INLINE)(typer)
        return stub

    return register


@_two_forms(lambda ar: 0, lambda ar: (ar[N_BLOCKS] << _MARK_SHIFT) | ar[USED])
def mark(ar) -> int:
    """The arena's level now, for :func:`release`."""


@_two_forms(lambda ar, level: None, _release_arena)
def release(ar, level: int) -> None:
    """Give back everything handed out since ``mark`` returned ``level`` (0: everything,
    the overflow blocks freed)."""


@_two_forms(lambda ar, n: _heap_f(n),
            lambda ar, n: numba.carray(_address(_reserve(ar, 8 * n), numba.float64), (n,)))
def empty_f(ar, n):
    """``np.empty(n)``."""


@_two_forms(lambda ar, n: _heap_i(n),
            lambda ar, n: numba.carray(_address(_reserve(ar, 8 * n), numba.int64), (n,)))
def empty_i(ar, n):
    """``np.empty(n, np.int64)``."""


@_two_forms(lambda ar, n: _heap_b(n),
            lambda ar, n: numba.carray(_address(_reserve(ar, n), numba.boolean), (n,)))
def empty_b(ar, n):
    """``np.empty(n, np.bool_)``."""


@_two_forms(lambda ar, like, n: _heap_like(like, n),
            lambda ar, like, n: numba.carray(_address(_reserve(ar, like.itemsize * n), like),
                                             (n,)))
def empty_like(ar, like, n):
    """``np.empty(n, like.dtype)`` (``like`` a 1-d array)."""


@_allocator
def empty_f2(ar, n, m):
    """``np.empty((n, m))``."""
    return empty_f(ar, n * m).reshape((n, m))


@_allocator
def empty_i2(ar, n, m):
    """``np.empty((n, m), np.int64)``."""
    return empty_i(ar, n * m).reshape((n, m))


@_allocator
def _fill(x, value):
    """``x[:] = value`` of a 1-d array; returns ``x``."""
    for i in range(x.shape[0]):
        x[i] = value
    return x


@_allocator
def zeros_f(ar, n):
    """``np.zeros(n)``."""
    return _fill(empty_f(ar, n), 0.0)


@_allocator
def zeros_f2(ar, n, m):
    """``np.zeros((n, m))``."""
    return _fill(empty_f(ar, n * m), 0.0).reshape((n, m))


@_allocator
def full_i(ar, n, value):
    """``np.full(n, value, np.int64)``."""
    return _fill(empty_i(ar, n), value)


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
    return _fill(empty_b(ar, n), value)


@_allocator
def _copy_into(x, src):
    """``x[:] = src`` of 1-d arrays; returns ``x``."""
    for i in range(src.shape[0]):
        x[i] = src[i]
    return x


@_allocator
def copy_f(ar, src):
    """``src.copy()`` of a 1-d float array."""
    return _copy_into(empty_f(ar, src.shape[0]), src)


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
    return _copy_into(empty_i(ar, src.shape[0]), src)


@_allocator
def full_i2(ar, n, m, value):
    """``np.full((n, m), value, np.int64)``."""
    return _fill(empty_i(ar, n * m), value).reshape((n, m))


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

