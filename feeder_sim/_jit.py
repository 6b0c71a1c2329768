"""The numba options every compiled kernel of feeder_sim is built with, in one place.

``cache=True``: compiled code is kept in ``__pycache__`` beside each module, so only the first
run on a machine pays for compilation. ``nogil=True``: kernels release the GIL, so a node's
executor threads keep serving callbacks while physics runs. ``error_model='numpy'``: a division
by zero gives inf/NaN as in numpy instead of raising, so a kernel costs no per-division check
and its results match the numpy reference it ports.
"""

import numba

JIT_OPTIONS = {'cache': True, 'nogil': True, 'error_model': 'numpy'}


def jit(fn):
    """Compile ``fn`` with :data:`JIT_OPTIONS`."""
    return numba.njit(**JIT_OPTIONS)(fn)


def inner(fn=None, *, inline: str = 'never'):
    """Compile ``fn`` for calls from other kernels only: no Python wrapper (less to compile).

    ``@inner(inline='always')`` also inlines it into each caller (for a tiny hot helper)."""
    compile_ = numba.njit(no_cpython_wrapper=True, inline=inline, **JIT_OPTIONS)
    return compile_ if fn is None else compile_(fn)
