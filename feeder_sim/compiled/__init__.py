"""feeder_sim's numba support: how kernels are compiled, cached, shared and given scratch memory.

Modules, each importing only those above it (and nothing else of feeder_sim):

* :mod:`.cache`: the keyed on-disk kernel cache (its key, directory, pruning and numba cache
  locator) and the flags of the patches that the key hashes.
* :mod:`.progress`: the first compile's progress lines or bar.
* :mod:`.ahead`: a first compile shared with a helper process compiling ahead from a recorded
  plan (``plans/<method>.json``), and the compile locks across processes.
* :mod:`.jit`: the numba options and the ``jit`` / ``inner`` decorators of every kernel module;
  importing it installs the cache, the locks, the compile notice and two patches of numba
  internals.
* :mod:`.arena`: scratch arenas for kernels (itself kernels, so it imports :mod:`.jit`).

So the import order is ``cache`` <- ``progress``, ``ahead`` <- ``jit`` <- ``arena``. This
package imports nothing itself: ``import feeder_sim.compiled.cache`` installs nothing.
"""
