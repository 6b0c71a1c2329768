"""A first compile shared by two processes: the run, and a helper compiling ahead of it.

numba compiles in one thread of one process (its compiler lock), most of it in Python (typing
and lowering: three fifths of the default run's first compile, LLVM the rest); a 2-core
machine leaves a core idle for a minute. Here, when a run starts compiling a stepping method's
kernels on a cold cache, it starts one helper process that compiles, from a *plan*, the
kernels the run will need last, into the same keyed cache (:mod:`.cache`); when the run gets
to them it loads them.

A plan (``plans/<method>.json``) is what a first run of the default scene compiled,
recorded by ``test/compile_plan.py``: every kernel and signature in the order their compiles
ended, each with its own compile time (callees' excluded) and the kernels its typing asked
for. :func:`helper_share` picks the helper's part, consecutive kernels of that order, by
simulating the two processes (:func:`simulate`).

Two processes must not compile one kernel at once (twice the work, and numba rewrites a
kernel's cache index as a whole: the last writer wins). Each compile of a package kernel that
misses the cache holds a lock file per kernel (``.locks/`` in the key directory): the second
process waits and then loads what the first saved. Locks are taken in call order down a chain
of kernels, which has no cycles, so no two processes wait on each other; a wait is bounded
all the same (:data:`LOCK_WAIT_S`), after which the waiting process compiles on its own.

The helper exits when its run does (its stdin is a pipe from the run), when its part is done,
or at once when another helper of the same plan and key is at work. $FEEDER_SIM_COMPILE_HELPER=0
turns it off. It changes no machine code: a kernel compiles the same in either process.
"""

from __future__ import annotations

import base64
from collections.abc import Iterator
import contextlib
import errno
import importlib
import json
import os
from pathlib import Path
import pickle
import subprocess
import sys
import threading
import time

from feeder_sim.compiled import cache

HELPER_ENV_VAR = 'FEEDER_SIM_COMPILE_HELPER'
PLAN_DIR = Path(__file__).resolve().parent / 'plans'
# A compile of one kernel takes at most some tens of seconds; the process holding the lock may
# also be stopped (a debugger, SIGSTOP). Past this the waiting process compiles on its own.
LOCK_WAIT_S = 300.0
_POLL_S = 0.02
# What starting the helper costs it before its first compile (interpreter, numpy, numba, the
# package), measured on a 2-core machine; the simulation of the two processes counts it.
HELPER_START_S = 2.5

_held: dict[str, int] = {}               # kernel -> lock file descriptor, this process
_lock_guard = threading.Lock()
_recording: list | None = None            # see record()
ready_hook = None       # called as each package kernel becomes ready (see progress.py)
_helper: dict = {'process': None}
_waited = {'s': 0.0, 'now': 0}            # see lock_wait_seconds(), waiting()


def waiting() -> bool:
    """Whether a thread of this process is waiting for another process's compile."""
    return _waited['now'] > 0


def lock_wait_seconds() -> float:
    """Wall time (s) this process has waited for compile locks outside numba's own compiler
    lock (whose holding :func:`.jit.kernel_load_seconds` counts): with it, all the time
    first use took."""
    return _waited['s']


def kernel_name(dispatcher) -> str | None:
    """``module:qualname`` of a package kernel a helper can import, else None."""
    py_func = getattr(dispatcher, 'py_func', None)
    code = getattr(py_func, '__code__', None)
    if code is None or '<locals>' in py_func.__qualname__:
        return None
    if not os.path.abspath(code.co_filename).startswith(cache.PACKAGE_ROOT + os.sep):
        return None
    # a kernel its module names (not an overload numba made of a Python function)
    if getattr(sys.modules.get(py_func.__module__), py_func.__qualname__, None) is not dispatcher:
        return None
    return f'{py_func.__module__}:{py_func.__qualname__}'


def _lock_path(name: str) -> Path | None:
    try:
        folder = cache.key_dir() / '.locks'
        folder.mkdir(exist_ok=True)
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None
    return folder / name.replace(':', '.')


def _open_lock(name: str) -> int:
    """A descriptor of lock file ``name``, or -1 where there is no shared cache to hold it."""
    path = _lock_path(name)
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o644) if path is not None else -1
    except OSError:
        return -1


@contextlib.contextmanager
def kernel_lock(name: str) -> Iterator[None]:
    """Hold ``name``'s compile lock (bounded wait, see the module).

    Re-entrant per process, not per thread: numba compiles one kernel at a time in a process
    (its compiler lock), and a thread that waited here on a lock another thread of its own
    process holds would wait with numba's lock held, for that other thread which needs it."""
    import fcntl

    with _lock_guard:
        if name in _held:
            fd = None
        else:
            outermost = not _held
            fd = _held[name] = -1
    if fd is None:
        yield
        return
    t0 = time.monotonic()
    fd = _open_lock(name)
    deadline = time.monotonic() + LOCK_WAIT_S
    _waited['now'] += 1
    try:
        while fd >= 0:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as e:
                if e.errno not in (errno.EAGAIN, errno.EACCES) or time.monotonic() > deadline:
                    break   # a file system without locks, or a stopped holder: unlocked
                time.sleep(_POLL_S)
    finally:
        _waited['now'] -= 1
    if outermost:
        _waited['s'] += time.monotonic() - t0
    try:
        yield
    finally:
        with _lock_guard:
            del _held[name]
        if fd >= 0:
            os.close(fd)   # releases the lock


def install_locks() -> None:
    """Put every compile of a package kernel that may miss the cache under its lock (and, while
    :func:`record` runs, on the record). Builds on ``Dispatcher.compile``: AttributeError if
    it moved."""
    from numba.core import sigutils
    from numba.core.dispatcher import Dispatcher

    compile_ = Dispatcher.compile
    if getattr(compile_, '_feeder_sim', False):
        return
    try:
        import fcntl  # noqa: F401 (POSIX only)
    except ImportError:
        return

    def locked_compile(self, sig):
        # typing asks again at every call site of a kernel compiled already: answered first
        args, _ = sigutils.normalize_signature(sig)
        if _recording is None and tuple(args) in self.overloads:
            return compile_(self, sig)
        try:
            name = self._feeder_sim_kernel
        except AttributeError:
            name = self._feeder_sim_kernel = kernel_name(self)
        if name is None:
            return compile_(self, sig)
        with kernel_lock(name):
            if _recording is None:
                out = compile_(self, sig)
            else:
                out = _recorded_compile(compile_, self, name, tuple(args))
        if ready_hook is not None:
            ready_hook(name)   # compiled here, or loaded from what the helper compiled
        return out

    locked_compile._feeder_sim = True
    Dispatcher.compile = locked_compile


# The record a plan is made of.

_stack: list[dict] = []


def _recorded_compile(compile_, dispatcher, name: str, args: tuple):
    key = (name, args)
    if _stack:
        _stack[-1]['deps'].append(key)
    known = tuple(args) in dispatcher.overloads
    frame = {'deps': [], 'start': time.perf_counter(), 'children_s': 0.0}
    _stack.append(frame)
    try:
        return compile_(dispatcher, args)
    finally:
        _stack.pop()
        spent = time.perf_counter() - frame['start']
        if _stack:
            _stack[-1]['children_s'] += spent
        if not known and _recording is not None:
            _recording.append({'kernel': name, 'args': args,
                               'cost_s': spent - frame['children_s'], 'deps': frame['deps']})


@contextlib.contextmanager
def record() -> Iterator[list]:
    """Record every package kernel compiled meanwhile (run on a cold cache): the list yielded
    fills with ``{'kernel', 'args', 'cost_s', 'deps'}`` in the order compiles end."""
    global _recording
    install_locks()
    _recording = []
    try:
        yield _recording
    finally:
        _recording = None


def encode_plan(records: list[dict]) -> dict:
    """The JSON form of a :func:`record`: deps as indices, signatures pickled."""
    import numba

    index = {(r['kernel'], r['args']): i for i, r in enumerate(records)}
    items = []
    for r in records:
        deps = sorted({index[d] for d in r['deps'] if d in index})
        items.append({'kernel': r['kernel'], 'cost_s': round(r['cost_s'], 3), 'deps': deps,
                      'signature': [str(a) for a in r['args']],
                      'args': base64.b64encode(pickle.dumps(r['args'], protocol=4)).decode()})
    share, wall = helper_share(items)
    return {'numba': numba.__version__, 'python': sys.implementation.cache_tag,
            'alone_s': round(sum(it['cost_s'] for it in items), 1),
            'with_helper_s': round(wall, 1), 'helper': share, 'items': items}


def load_plan(method: str) -> dict | None:
    """The shipped plan of ``method`` if this Python can read it, else None."""
    try:
        plan = json.loads((PLAN_DIR / f'{method}.json').read_text())
    except (OSError, ValueError):
        return None
    # another numba may read the pickled types otherwise or not at all: the helper then
    # compiles what nobody asks for, or skips the item
    return plan if plan.get('python') == sys.implementation.cache_tag else None


def simulate(costs: list[float], deps: list[list[int]], share: set[int],
             helper_start_s: float = HELPER_START_S) -> float:
    """Simulated wall time (s) of a first compile with the helper taking ``share``.

    The run compiles the items in order and waits at each of the helper's until it is done.
    The helper takes, of its share, the first item whose dependencies are done; it waits for
    the run's items it depends on (the run's to compile, not the helper's). The two timelines
    wait on each other, so they are computed in turn until they settle."""
    n = len(costs)
    order = sorted(share)
    helper_done: dict[int, float] = {}
    run_done = [0.0] * n
    end = 0.0
    for _ in range(8):
        t = 0.0
        for i in range(n):
            t = max(t, helper_done.get(i, 0.0)) if i in share else t + costs[i]
            run_done[i] = t
        previous, helper_done = helper_done, {}
        pending, t_h = list(order), helper_start_s
        while pending:
            pick, start = 0, None
            for k, i in enumerate(pending):
                if any(d in share and d not in helper_done for d in deps[i]):
                    continue
                ready = max((helper_done[d] if d in share else run_done[d] for d in deps[i]),
                            default=0.0)
                if start is None or max(t_h, ready) < start:
                    pick, start = k, max(t_h, ready)
                if start <= t_h:
                    break
            i = pending.pop(pick)
            t_h = start + costs[i]
            helper_done[i] = t_h
        end = t
        if helper_done == previous:
            break
    return end


def helper_share(items: list[dict], helper_start_s: float = HELPER_START_S
                 ) -> tuple[list[int], float]:
    """The helper's items, a run of consecutive ones in the run's order (the callees of one
    part of the work), chosen where the simulated wall time is least, and that time (s)."""
    costs = [it['cost_s'] for it in items]
    deps = [it['deps'] for it in items]
    n = len(items)
    best, best_t = [], sum(costs)
    for length in range(n, 0, -1):
        for first in range(n - length, -1, -1):
            share = range(first, first + length)
            wall = simulate(costs, deps, set(share), helper_start_s)
            if wall < best_t - 1e-9:
                best, best_t = list(share), wall
    return best, best_t


def _watch_parent() -> None:
    # stdin is a pipe from the run: its end is the run's end
    try:
        while sys.stdin.buffer.read(4096):
            pass
    finally:
        os._exit(0)


# What the helper waits, in all, for kernels of the run's part it needs: little in the order
# simulated; a run of another scene may never compile them.
_DEP_WAIT_S = 60.0


def _helper_main(method: str) -> int:
    os.environ[HELPER_ENV_VAR] = '0'
    threading.Thread(target=_watch_parent, daemon=True).start()
    plan = load_plan(method)
    if plan is None:
        return 0
    with _exclusive(f'helper:{method}') as alone:
        if alone:
            _compile_share(plan)
    return 0


@contextlib.contextmanager
def _exclusive(name: str) -> Iterator[bool]:
    """Hold lock ``name`` if free: whether it was."""
    import fcntl

    fd = _open_lock(name)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            free = True
        except OSError:
            free = False
        yield free
    finally:
        if fd >= 0:
            os.close(fd)


def _compile_share(plan: dict) -> None:
    """Compile the helper's items: each time the first whose dependencies are done, waiting
    (up to :data:`_DEP_WAIT_S` in all) for those that are the run's."""
    items = plan['items']
    share = set(plan['helper'])
    pending, done, cached = list(plan['helper']), set(), set()

    def ready(i: int) -> bool:
        for d in items[i]['deps']:
            if d in share and d not in done:
                return False
            if d not in share and d not in cached:
                if not _in_cache(items[d]):
                    return False
                cached.add(d)
        return True

    waited = 0.0
    while pending:
        pick = next((k for k, i in enumerate(pending) if ready(i)), None)
        if pick is None:
            if waited < _DEP_WAIT_S:
                time.sleep(0.1)
                waited += 0.1
                continue
            pick = 0
        i = pending.pop(pick)
        try:
            _dispatcher(items[i]).compile(_args(items[i]))
        except Exception:  # noqa: BLE001 (a stale plan: the run compiles what it needs)
            pass
        done.add(i)


def _dispatcher(item: dict):
    module, _, qualname = item['kernel'].partition(':')
    return getattr(importlib.import_module(module), qualname)


def _args(item: dict) -> tuple:
    return pickle.loads(base64.b64decode(item['args']))


def cached(dispatcher, args: tuple) -> bool:
    """Whether ``dispatcher`` has ``args`` compiled here or in its cache's index (read, not
    loaded). Builds on numba's cache internals: AttributeError if they moved."""
    if args in dispatcher.overloads:
        return True
    cache = dispatcher._cache
    return cache._index_key(args, dispatcher.targetctx.codegen()) in \
        cache._cache_file._load_index()


def _in_cache(item: dict) -> bool:
    """:func:`cached` for a plan's item; True if that cannot be told (the helper then goes on:
    the lock keeps the two processes from compiling it twice)."""
    try:
        return cached(_dispatcher(item), _args(item))
    except Exception:  # noqa: BLE001 (a stale plan, or numba's cache internals moved)
        return True


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:   # not Linux
        return os.cpu_count() or 1


# The helper's program. jit first: its install() sets the flags the cache's key hashes (the
# patches' switches) and the compile locks, before this module takes a key for the helper's
# lock; this module does not import jit (jit imports it). Not a normal exit: the thread reading
# stdin would hold its lock at shutdown (abort).
_HELPER_PROGRAM = '''
import os, sys
from feeder_sim.compiled import jit
from feeder_sim.compiled import ahead
os._exit(ahead._helper_main(sys.argv[1]))
'''


def start_helper(method: str) -> bool:
    """Start the helper for ``method``'s plan unless it is off, pointless or started: whether
    it started."""
    if os.environ.get(HELPER_ENV_VAR, '1').strip() == '0' or _helper['process'] is not None:
        return False
    if _cores() < 2 or load_plan(method) is None or _lock_path(f'helper:{method}') is None:
        return False   # one core, no plan, or no shared cache for the helper to fill
    # this very package, whatever the helper's sys.path would find first
    parent = os.path.dirname(cache.PACKAGE_ROOT)
    path = os.pathsep.join(p for p in (parent, os.environ.get('PYTHONPATH')) if p)
    try:
        process = subprocess.Popen(
            [sys.executable, '-c', _HELPER_PROGRAM, method],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, HELPER_ENV_VAR: '0', 'PYTHONPATH': path})
    except OSError:
        return False
    _helper['process'] = process
    threading.Thread(target=process.wait, daemon=True).start()   # no zombie once it is done
    return True
