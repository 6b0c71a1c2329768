"""The numba options every compiled kernel of feeder_sim is built with, and where it is cached.

``cache=True``: compiled code is kept on disk, so only the first run pays for compilation (a
minute or more). numba's own scheme keys each file's cache on that file alone, in
``__pycache__`` beside it, which fails three ways: an install elsewhere (colcon's ``install/``,
another venv) compiles everything again; a kernel that calls a kernel of another file keeps
the old callee's machine code after that file changes; and cache entries still name a module
after it is renamed, so loading them fails. Here the whole set is keyed instead on a hash of
the package's kernel sources (see :func:`key_material`) with the Python, numba and numpy
versions, and kept in a per-user directory with one subdirectory per key: $FEEDER_SIM_CACHE_DIR,
else $NUMBA_CACHE_DIR/feeder_sim (numba's own override is honoured), else
$XDG_CACHE_HOME/feeder_sim or ~/.cache/feeder_sim. Any kernel change anywhere starts a fresh
set; the same sources at another path reuse it; the few most recently used sets are kept. A
compile is long and otherwise silent, so it is announced by one line on stderr when (and only
when) one starts. The scheme is a cache locator put in front of numba's own (a private numba
interface): a numba without it gets plain ``cache=True`` and one warning line.

Kernels that only other kernels call (:func:`inner`) get no machine code of their own: numba
would compile each of them on its own and again inside every caller (see
:func:`_defer_codegen`; $FEEDER_SIM_DEFER_CODEGEN=0 turns this off).

``nogil=True``: kernels release the GIL, so a node's executor threads keep serving callbacks
while physics runs. ``error_model='numpy'``: a division by zero gives inf/NaN as in numpy
instead of raising, so a kernel costs no per-division check and its results match the numpy
reference it ports.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
import functools
import hashlib
import os
from pathlib import Path
import re
import shutil
import sys

import numba
import numpy as np

from feeder_sim import _compile_ahead, _compile_progress

JIT_OPTIONS = {'cache': True, 'nogil': True, 'error_model': 'numpy'}


def jit(fn: Callable) -> Callable:
    """Compile ``fn`` with :data:`JIT_OPTIONS`."""
    return numba.njit(**JIT_OPTIONS)(fn)


def inner(fn: Callable | None = None, *, inline: str = 'never',
          machine_inline: bool = False) -> Callable:
    """Compile ``fn`` for calls from other kernels only: no Python wrapper (less to compile).

    ``@inner(inline='always')`` inlines it into each caller's numba IR (typed again there:
    costly to compile). ``@inner(machine_inline=True)`` has LLVM inline the compiled function
    instead (numba's ``forceinline``), nearly free to compile: for tiny helpers called
    everywhere, where numba's calling convention (status word, arguments by pointer, a
    reference-count call per array) costs more than their body.

    Such a kernel gets no machine code of its own (see :func:`_defer_codegen`): its code is
    compiled into each ``jit`` kernel that calls it, and its cache entry is its IR."""
    compile_ = numba.njit(no_cpython_wrapper=True, inline=inline, forceinline=machine_inline,
                          **JIT_OPTIONS)
    return compile_ if fn is None else compile_(fn)


# The keyed cache. Everything below applies to files under PACKAGE_ROOT only; other numba code
# in the process keeps numba's own locators.

ENV_VAR = 'FEEDER_SIM_CACHE_DIR'
# '0': every kernel gets machine code of its own as numba does by default (see _defer_codegen):
# the same results, a slower first compile. For comparing the two, and a way out should a numba
# release change what the deferral relies on in a way it cannot detect.
DEFER_ENV_VAR = 'FEEDER_SIM_DEFER_CODEGEN'
INLINE_ENV_VAR = 'FEEDER_SIM_INLINE_REFCOUNTS'
_IR_CACHE_KIND = 'feeder_sim:ir'
PACKAGE_ROOT = os.path.dirname(os.path.abspath(__file__))
PACKAGE = os.path.basename(PACKAGE_ROOT)

# Key directories kept besides the current one: a few for switching branches or installs,
# not one per edit of a kernel (a full set is some tens of MB).
_KEEP = 4
_KEY_DIR = re.compile(r'^[\w.-]+-numba[\w.+]+-[0-9a-f]{16}$')
_LAST_USED = '.last_used'
# What a first run of one stepping method compiles, measured on a 2-core machine: under 10 s
# (impulse_based), 50-59 s (event_driven), 80-100 s (time_stepping); the test suite minutes.
_COLD_COMPILE = '10-100 s'

_state = {'notice_dir': None, 'noticed': False, 'warned': False, 'deferred_codegen': False,
          'inline_refcounts': False, 'expected': None, 'progress': None}


def expect(method: str) -> None:
    """Name the stepping method whose kernels this process compiles next: a first compile
    then shares its work with a helper process (:mod:`._compile_ahead`)."""
    _state['expected'] = method


def cache_root() -> Path:
    """The directory holding one subdirectory per key: $FEEDER_SIM_CACHE_DIR, else
    $NUMBA_CACHE_DIR/feeder_sim (numba's own override, e.g. for a read-only home), else
    $XDG_CACHE_HOME/feeder_sim, else ~/.cache/feeder_sim."""
    if os.environ.get(ENV_VAR):
        root = Path(os.environ[ENV_VAR])
    elif numba.config.CACHE_DIR:
        root = Path(numba.config.CACHE_DIR) / PACKAGE
    else:
        xdg = os.environ.get('XDG_CACHE_HOME')
        root = (Path(xdg) if xdg else Path.home() / '.cache') / PACKAGE
    # absolute: numba keeps the path, and a process may change directory later
    return Path(os.path.abspath(root.expanduser()))


def _module_file(root: str, parts: list[str]) -> str | None:
    base = os.path.join(root, *parts)
    for candidate in (base + '.py', os.path.join(base, '__init__.py')):
        if os.path.isfile(candidate):
            return candidate
    return None


def _package_imports(root: str, rel: str, tree: ast.Module) -> list[tuple[str, set[str] | None]]:
    """(file, imported names or None for the whole module) of each import from the package."""
    package = os.path.basename(root)
    here = rel.split(os.sep)[:-1]
    found = []
    # Module level only: kernels cannot import, and a module's globals are bound there.
    for node in tree.body:
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split('.')
                if parts[0] == package and (f := _module_file(root, parts[1:])):
                    found.append((f, None))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[:len(here) - node.level + 1] if node.level <= len(here) + 1 else None
                if base is None:
                    continue
                parts = base + (node.module.split('.') if node.module else [])
            else:
                parts = (node.module or '').split('.')
                if parts[0] != package:
                    continue
                parts = parts[1:]
            for alias in node.names:
                if submodule := _module_file(root, [*parts, alias.name]):
                    found.append((submodule, None))
                elif module := _module_file(root, parts):
                    found.append((module, {alias.name}))
    return found


def _constants(tree: ast.Module, names: set[str] | None) -> list[str]:
    """The module-level assignments of ``names`` (of all if None), as syntax trees."""
    out = []
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            bound = {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
            if names is None or bound & names:
                out.append(ast.dump(node))
    return out


def key_material(root: str = PACKAGE_ROOT) -> list[tuple[str, str]]:
    """What the key hashes, as (path relative to ``root``, text) pairs.

    The full source of every kernel module (one importing ``_jit``) and of ``_jit`` itself; the
    module-level assignments that kernel modules import from other modules of the package
    (numba freezes globals into the machine code); and where each NamedTuple class of the
    package is defined (the cache index records argument types by module and name, so a moved
    class would make numba fail to read the index)."""
    jit_file = os.path.join(root, '_jit.py')
    sources: dict[str, str] = {}
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if not d.startswith(('.', '__')))
        for name in sorted(files):
            if name.endswith('.py'):
                path = os.path.join(folder, name)
                with open(path, encoding='utf-8') as f:
                    sources[path] = f.read()
    material = []
    trees: dict[str, ast.Module] = {}
    imports: dict[str, list] = {}
    for path, source in sources.items():
        rel = os.path.relpath(path, root)
        if path != jit_file and re.search(r'^(?:from|import)\s.*\b_jit\b', source, re.M):
            trees[path] = ast.parse(source, path)
            imports[path] = _package_imports(root, rel, trees[path])
        material += [(rel, f'NamedTuple {m}')
                     for m in re.findall(r'^class (\w+)\(\s*(?:typing\.)?NamedTuple\b', source,
                                         re.M)]
    kernels = {path for path, found in imports.items() if any(f == jit_file for f, _ in found)}
    kernels.add(jit_file)
    for path in sorted(kernels):
        material.append((os.path.relpath(path, root), sources[path]))
    for path in sorted(kernels - {jit_file}):
        for module, names in imports[path]:
            if module in kernels or module not in sources:
                continue
            tree = trees.get(module) or ast.parse(sources[module], module)
            trees[module] = tree
            material += [(os.path.relpath(module, root), text)
                         for text in _constants(tree, names)]
    return sorted(set(material))


def cache_key(root: str = PACKAGE_ROOT) -> str:
    """The name of the key directory: the kernel sources' hash with the versions of everything
    that shapes the machine code."""
    h = hashlib.sha256()
    # deferred or not: a deferred function's cache entry is in a form numba cannot read alone;
    # inlined reference counts or not: the same results from other machine code
    for part in (sys.implementation.cache_tag, getattr(sys, 'abiflags', ''),
                 numba.__version__, np.__version__, str(_state['deferred_codegen']),
                 str(_state['inline_refcounts'])):
        h.update(part.encode() + b'\0')
    for rel, text in key_material(root):
        h.update(rel.replace(os.sep, '/').encode() + b'\0' + text.encode() + b'\0')
    return f'{sys.implementation.cache_tag}-numba{numba.__version__}-{h.hexdigest()[:16]}'


def key_dir() -> Path:
    """This package's key directory; marks it used, and makes room if it is new.

    Raises OSError (unwritable, unreadable) or SyntaxError (a module being edited)."""
    found = _key_dir()
    if isinstance(found, Exception):
        raise found
    return found


@functools.cache
def _key_dir() -> Path | Exception:
    # Once per process, failure included: every kernel's decoration asks.
    try:
        return _make_key_dir()
    except (OSError, SyntaxError, UnicodeDecodeError) as e:
        return e


def _make_key_dir() -> Path:
    path = cache_root() / cache_key()
    new = not path.is_dir()
    path.mkdir(parents=True, exist_ok=True)
    (path / _LAST_USED).touch()
    if new:
        _prune(path.parent, keep=path.name)
    return path


def _prune(root: Path, keep: str) -> None:
    def last_used(d: Path) -> float:
        try:
            return (d / _LAST_USED).stat().st_mtime
        except OSError:
            return 0.0

    # Only directories named like keys: the root may be a directory the user shares.
    others = sorted((d for d in root.iterdir()
                     if d.name != keep and _KEY_DIR.match(d.name) and d.is_dir()),
                    key=last_used, reverse=True)
    # A process still using a removed key only recompiles: numba recreates the directory on
    # save and treats missing cache files as misses.
    for d in others[_KEEP:]:
        shutil.rmtree(d, ignore_errors=True)


def _warn(message: str) -> None:
    if not _state['warned']:
        _state['warned'] = True
        print(f'{PACKAGE}: {message}', file=sys.stderr, flush=True)


def _make_locator(base: type) -> type:
    class PackageLocator(base):
        """Caches the functions of files under ``PACKAGE_ROOT`` in the key directory, at the
        file's folder relative to the package (two ``_kernels.py`` would clash otherwise), with
        the key as the source stamp, so that the same sources at any path share one cache."""

        def __init__(self, py_func, py_file: str, rel: str, key_path: Path) -> None:
            self._py_file = py_file  # numba's warnings about uncachable functions read it
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(key_path.joinpath(*Path(rel).parent.parts))
            self._stamp = key_path.name

        def get_cache_path(self) -> str:
            return self._cache_path

        def get_source_stamp(self) -> str:
            return self._stamp

        def get_disambiguator(self) -> str:
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file: str):
            try:
                rel = os.path.relpath(os.path.abspath(py_file), PACKAGE_ROOT)
            except ValueError:  # another drive
                return None
            if rel.startswith(os.pardir) or not rel.endswith('.py'):
                return None
            try:
                self = cls(py_func, py_file, rel, key_dir())
                self.ensure_cache_path()
            except (OSError, SyntaxError, UnicodeDecodeError) as e:
                _warn(f'no kernel cache in {cache_root()} ({e}); numba caches beside the '
                      'modules instead')
                return None  # numba's own locators are next in line
            _state['notice_dir'] = key_dir()
            return self

    return PackageLocator


_load_timer = None   # numba's TimingListener on its compiler lock, once installed


def kernel_load_seconds() -> float:
    """Wall time (s) this process has spent loading kernels from the cache and compiling them
    (in numba's compiler lock, or waiting for another process compiling one, see
    :mod:`._compile_ahead`). A caller timing its own work subtracts what this grew by, so that
    a first use does not count as the work's cost."""
    timer = _load_timer
    held = timer.duration if timer is not None and timer.done else 0.0
    return held + _compile_ahead.lock_wait_seconds()


_holding = {'depth': 0}   # numba's compiler lock, held by this process: how deep


def in_first_use() -> bool:
    """Whether this process is loading or compiling a kernel now (holding numba's compiler
    lock, or waiting for another process compiling one). A first compile cannot be cut
    short; a caller that must stop within a second (the node) does its finishing meanwhile."""
    return _holding['depth'] > 0 or _compile_ahead.waiting()


def _listen_for_compiles() -> None:
    global _load_timer
    from numba.core import event

    # the lock is re-entrant: numba's timer counts the outermost hold only
    _load_timer = event.TimingListener()
    event.register('numba:compiler_lock', _load_timer)

    class Holding(event.Listener):
        def on_start(self, ev) -> None:
            _holding['depth'] += 1

        def on_end(self, ev) -> None:
            _holding['depth'] -= 1

    event.register('numba:compiler_lock', Holding())

    def ours(ev) -> bool:
        py_func = getattr((ev.data or {}).get('dispatcher'), 'py_func', None)
        filename = getattr(getattr(py_func, '__code__', None), 'co_filename', '')
        return os.path.abspath(filename).startswith(PACKAGE_ROOT + os.sep)

    class Notice(event.Listener):
        def on_start(self, ev) -> None:
            progress = _state['progress']
            if progress is not None and progress.running() or not ours(ev):
                return
            if not _state['noticed']:
                _state['noticed'] = True
                where = _state['notice_dir'] or '__pycache__ beside the modules'
                helped = bool(_state['expected']) and _compile_ahead.start_helper(
                    _state['expected'])
                print(f'{PACKAGE}: compiling numba kernels for first use (about '
                      f'{_COLD_COMPILE}{", in two processes" if helped else ""}, cached in '
                      f'{where})', file=sys.stderr, flush=True)
            if _compile_progress.wanted():
                plan = _compile_ahead.load_plan(_state['expected']) if _state['expected'] \
                    else None
                progress = _compile_progress.CompileProgress(
                    _compile_progress.plan_costs(plan), lambda: _holding['depth'] > 0)
                _state['progress'] = progress
                _compile_ahead.ready_hook = progress.compiled
                progress.start()

        def on_end(self, ev) -> None:
            pass

    event.register('numba:compile', Notice())


def _defer_codegen() -> None:
    """A compiled function without a Python wrapper gets machine code only when something asks.

    numba links the LLVM module of every compiled callee into its caller's, then optimizes and
    generates machine code for the caller's whole module, callees included. It also does both
    for each callee's own module the moment the callee is compiled, although the code of a
    function without a Python wrapper (an :func:`inner` kernel, an implementation of a numpy
    function) runs only as linked into its callers. Down a chain of kernels that repeated work
    is a large part of a first compile. Here such a module keeps its function-level optimized
    IR for callers to link, and is optimized and compiled only if its code is asked for (a
    pointer, its assembly). Its cache entry is that IR (numba's holds machine code too), which
    another process links into new callers as it would have linked the compiled function. Its
    entry point is the one numba gives every function without a Python wrapper: address 0,
    never called. Builds on numba internals: ImportError or AttributeError if they moved."""
    import llvmlite.binding as ll
    from numba._dynfunc import make_function
    from numba.core import codegen, cpu

    library_class, context_class = codegen.JITCodeLibrary, cpu.CPUContext
    codegen_class = codegen.JITCPUCodegen
    if getattr(context_class.get_executable, '_feeder_sim', False):
        return
    get_executable = context_class.get_executable
    optimize_final_module = library_class._optimize_final_module
    finalize_final_module = library_class._finalize_final_module
    serialize = library_class.serialize_using_object_code
    unserialize = library_class._unserialize.__func__
    set_env = codegen_class.set_env
    demands_code = {name: getattr(library_class, name)
                    for name in ('get_pointer_to_function', '_get_compiled_object', 'get_asm_str')}
    library_class._finalize_dynamic_globals  # noqa: B018 (AttributeError if it moved)

    def deferred_executable(self, library, fndesc, env):
        deferred = getattr(library, '_feeder_sim_deferred', False)
        # (a library loaded from numba's own cache entry comes finalized, its module empty)
        if not deferred and not library._finalized:
            try:
                library._final_module.get_function(fndesc.llvm_cpython_wrapper_name)
            except NameError:
                deferred = library._feeder_sim_deferred = True
        if not deferred:
            return get_executable(self, library, fndesc, env)
        return make_function(fndesc.lookup_module(), fndesc.qualname.split('.')[-1],
                             f'no Python wrapper: {fndesc.qualname}', 0, env, (library,))

    def serialize_as_ir(self):
        # a cache entry of a deferred function is its IR (numba's is machine code and IR)
        if getattr(self, '_feeder_sim_deferred', False):
            self._ensure_finalized()
            return (self.name, _IR_CACHE_KIND, self._final_module.as_bitcode())
        return serialize(self)

    def unserialize_ir(cls, codegen, state):
        name, kind, data = state
        if kind != _IR_CACHE_KIND:
            return unserialize(cls, codegen, state)
        self = codegen.create_library(name)
        self._final_module = ll.parse_bitcode(data)
        self._feeder_sim_deferred = True
        self._finalize_final_module()
        return self

    def set_env_if_defined(self, env_name, env):
        # the environment variable of a function that has no machine code is nowhere yet
        if self._engine.get_global_value_address(env_name):
            set_env(self, env_name, env)

    def optimize_unless_deferred(self):
        if not getattr(self, '_feeder_sim_deferred', False):
            optimize_final_module(self)

    def finalize_unless_deferred(self):
        if getattr(self, '_feeder_sim_deferred', False):
            self._finalize_dynamic_globals()  # callers read them from the linked IR too
            self._finalized = True
        else:
            finalize_final_module(self)

    def materialized(method):
        def demand(self, *args, **kwargs):
            if getattr(self, '_feeder_sim_deferred', False):
                self._ensure_finalized()
                self._feeder_sim_deferred = False
                self._dynamic_globals.clear()
                # the class's own steps, so that whatever else is installed on them applies
                self._optimize_final_module()
                self._finalize_final_module()
            return method(self, *args, **kwargs)
        return demand

    deferred_executable._feeder_sim = True
    context_class.get_executable = deferred_executable
    library_class.serialize_using_object_code = serialize_as_ir
    library_class._unserialize = classmethod(unserialize_ir)
    codegen_class.set_env = set_env_if_defined
    library_class._optimize_final_module = optimize_unless_deferred
    library_class._finalize_final_module = finalize_unless_deferred
    for name, method in demands_code.items():
        setattr(library_class, name, materialized(method))


def _switch(name: str, off_means: str) -> bool:
    """An on/off environment variable, on unless it is 0; anything but 0 or 1 gets one line."""
    value = os.environ.get(name, '1').strip() or '1'
    if value not in ('0', '1'):
        print(f'{PACKAGE}: {name}={value!r} is neither 0 nor 1; taken as 1 (set it to 0 '
              f'{off_means})', file=sys.stderr, flush=True)
    return value != '0'


# calls of numba's reference counting in an optimized module, and the null tests put in their
# place (inlined, then the call is made only for an array with an owner)
_NRT_CALL = re.compile(r'(call [^\n@]*void )@NRT_(incref|decref)\(')
_NRT_TESTED = '''
define internal void @NRT_{op}_tested(ptr %owner) alwaysinline {{
  %owned = icmp ne ptr %owner, null
  br i1 %owned, label %count, label %done
count:
  call void @NRT_{op}(ptr %owner)
  br label %done
done:
  ret void
}}
'''


def _inline_refcounts() -> None:
    """Test an array's owner for null inline before calling numba's reference counting.

    numba defines ``NRT_incref`` / ``NRT_decref`` ``noinline``, so that its pruning pass can
    pair them up as calls while it optimizes a module, and leaves them calls after it: every
    array handed to a compiled function that is not inlined costs two, even an array without
    an owner, whose count is never touched (the arenas' arrays, :func:`._arena.borrow`). Such
    a call does nothing but a null test, yet it spills the caller's floating-point registers:
    a small time step made some 1 400 of them. Here, once numba has optimized (and pruned) the
    module of a function that gets machine code, every such call is put behind an inlined
    null test; the calls made for arrays with an owner and the pairs pruned are the same.
    Inlining the counting itself instead (an atomic update, fences and a destructor call at
    each of several thousand places) doubled the machine-code generation of the step's
    module for no further gain.

    Applies to every function numba compiles in this process. Builds on numba internals
    (``JITCodeLibrary._optimize_final_module``): AttributeError if they moved."""
    import llvmlite.binding as ll
    from numba.core import codegen

    library_class = codegen.JITCodeLibrary
    optimize_final_module = library_class._optimize_final_module
    if getattr(optimize_final_module, '_feeder_sim_inline', False):
        return

    def optimize_then_inline(self):
        optimize_final_module(self)
        if getattr(self, '_feeder_sim_deferred', False):
            return  # no machine code: its callers' modules are inlined in turn
        ops = set()

        def tested(call):
            ops.add(call[2])
            return f'{call[1]}@NRT_{call[2]}_tested('

        text = _NRT_CALL.sub(tested, str(self._final_module))
        if not ops:
            return
        try:
            module = ll.parse_assembly(text + ''.join(_NRT_TESTED.format(op=op) for op in ops))
        except RuntimeError as e:  # an LLVM whose IR reads otherwise (typed pointers)
            _warn(f'reference-count calls left as numba makes them (slower small steps): '
                  f'{str(e).splitlines()[0]}; {INLINE_ENV_VAR}=0 skips the attempt')
            return
        module.name = self._final_module.name
        builder = ll.create_pass_builder(self._codegen._tm, ll.create_pipeline_tuning_options())
        passes = ll.create_new_module_pass_manager()
        passes.add_always_inliner_pass()
        passes.add_simplify_cfg_pass()
        passes.run(module, builder)
        self._final_module = module

    optimize_then_inline._feeder_sim_inline = True
    library_class._optimize_final_module = optimize_then_inline


def install() -> bool:
    """Route this package's kernels to the keyed cache and announce a first compile.

    Returns False, after one line on stderr, if this numba lacks the internals the locator
    builds on; kernels then use numba's own ``cache=True`` (beside each module)."""
    try:
        _listen_for_compiles()
    except (ImportError, AttributeError, TypeError):
        pass  # a notice only
    try:
        if _switch(DEFER_ENV_VAR, 'to give every kernel machine code of its own'):
            _defer_codegen()
            _state['deferred_codegen'] = True
    except (ImportError, AttributeError):
        pass  # callee-only kernels get machine code of their own: a slower first compile
    try:
        if _switch(INLINE_ENV_VAR, 'to keep numba\'s out-of-line reference counting'):
            _inline_refcounts()
            _state['inline_refcounts'] = True
    except (ImportError, AttributeError):
        pass  # numba's out-of-line reference counting: slower small steps
    try:
        _compile_ahead.install_locks()
    except (ImportError, AttributeError):
        pass  # two processes may compile a kernel at once: twice the work, the same code
    try:
        from numba.core import caching
        impl = getattr(caching, 'CacheImpl', None) or caching._CacheImpl
        locators = impl._locator_classes
        base = caching._CacheLocator
    except (ImportError, AttributeError) as e:
        _warn(f'numba {numba.__version__} has no cache locator hook ({e}); kernels are '
              'cached beside their modules')
        return False
    if not any(getattr(c, '_feeder_sim_root', None) == PACKAGE_ROOT for c in locators):
        locator = _make_locator(base)
        locator._feeder_sim_root = PACKAGE_ROOT
        locators.insert(0, locator)
    return True


# Before any kernel is decorated: numba picks a function's cache locator at decoration time.
install()
