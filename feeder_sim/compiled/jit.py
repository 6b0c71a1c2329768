"""The numba options every compiled kernel of feeder_sim is built with, and what happens when one
compiles.

:func:`jit` and :func:`inner` are the decorators of every kernel module. Importing this module
installs (:func:`install`), before any kernel is decorated: the keyed cache (:mod:`.cache`), the
compile locks shared with a helper process (:mod:`.ahead`), the first compile's notice and
progress (:mod:`.progress`), and three patches of numba internals. A compile is long and
otherwise silent, so it is announced by one line on stderr when (and only when) one starts.

Compiled functions are numbered apart from those of any other process (see
:func:`_unique_function_names`): code linked from the cache, compiled elsewhere, must never
share a name with different code compiled here.

Kernels that only other kernels call (:func:`inner`) get no machine code of their own: numba
would compile each of them on its own and again inside every caller (see
:func:`_defer_codegen`; $FEEDER_SIM_DEFER_CODEGEN=0 turns this off). Calls of numba's reference
counting are put behind an inlined null test (see :func:`_inline_refcounts`;
$FEEDER_SIM_INLINE_REFCOUNTS=0 turns this off). Either way the results are the same.

``cache=True``: compiled code is kept on disk (:mod:`.cache`), so only the first run pays for
compilation. ``nogil=True``: kernels release the GIL, so a node's executor threads keep serving
callbacks while physics runs. ``error_model='numpy'``: a division by zero gives inf/NaN as in
numpy instead of raising, so a kernel costs no per-division check and its results match the
numpy reference it ports.
"""

from __future__ import annotations

from collections.abc import Callable
import inspect
import itertools
import os
import re
import secrets
import sys

import numba

from feeder_sim.compiled import ahead, cache, progress

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


def for_python(kernel: Callable) -> Callable:
    """The :func:`jit` kernel through which Python calls the :func:`inner` kernel ``kernel``
    (named ``<name>_inline``): named ``<name>``, of the same parameters, passed on.

    Kernels call the inner form, compiled into each of them (and inlined by LLVM, with
    ``machine_inline``); a call from Python needs a kernel with a Python wrapper. The
    wrapper is made here, not written out beside each such kernel, and is compiled (and
    cached) as if it stood on the inner kernel's line of its module."""
    py_func = kernel.py_func
    name = py_func.__name__.removesuffix('_inline')
    params = inspect.signature(py_func).parameters.values()
    if name == py_func.__name__ or any(p.kind is not p.POSITIONAL_OR_KEYWORD
                                       or p.default is not p.empty for p in params):
        raise TypeError(f'for_python: {py_func.__qualname__} must be named <name>_inline and '
                        'take positional parameters without defaults')
    names = ', '.join(p.name for p in params)
    code = py_func.__code__
    source = f'def {name}({names}):\n    return kernel({names})\n'
    source = '\n' * (code.co_firstlineno - 1) + source
    namespace = {'__name__': py_func.__module__, 'kernel': kernel}
    exec(compile(source, code.co_filename, 'exec'), namespace)  # noqa: S102 (our own names)
    wrapper = namespace[name]
    wrapper.__doc__ = f':func:`{py_func.__name__}` for Python callers.'
    return jit(wrapper)


# The patches' switches: '0' turns one off. DEFER_ENV_VAR '0': every kernel gets machine code
# of its own as numba does by default (see _defer_codegen): the same results, a slower first
# compile. For comparing the two, and a way out should a numba release change what the deferral
# relies on in a way it cannot detect.
DEFER_ENV_VAR = 'FEEDER_SIM_DEFER_CODEGEN'
INLINE_ENV_VAR = 'FEEDER_SIM_INLINE_REFCOUNTS'
_IR_CACHE_KIND = 'feeder_sim:ir'

# What a first run of one stepping method compiles, measured on a 2-core machine: under 10 s
# (impulse_based), 50-59 s (event_driven), 80-100 s (time_stepping); the test suite minutes.
_COLD_COMPILE = '10-100 s'

_state = {'noticed': False, 'expected': None, 'progress': None}


def expect(method: str) -> None:
    """Name the stepping method whose kernels this process compiles next: a first compile
    then shares its work with a helper process (:mod:`.ahead`)."""
    _state['expected'] = method


_load_timer = None   # numba's TimingListener on its compiler lock, once installed


def kernel_load_seconds() -> float:
    """Wall time (s) this process has spent loading kernels from the cache and compiling them
    (in numba's compiler lock, or waiting for another process compiling one, see
    :mod:`.ahead`). A caller timing its own work subtracts what this grew by, so that a first
    use does not count as the work's cost."""
    timer = _load_timer
    held = timer.duration if timer is not None and timer.done else 0.0
    return held + ahead.lock_wait_seconds()


_holding = {'depth': 0}   # numba's compiler lock, held by this process: how deep


def in_first_use() -> bool:
    """Whether this process is loading or compiling a kernel now (holding numba's compiler
    lock, or waiting for another process compiling one). A first compile cannot be cut
    short; a caller that must stop within a second (the node) does its finishing meanwhile."""
    return _holding['depth'] > 0 or ahead.waiting()


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
        return os.path.abspath(filename).startswith(cache.PACKAGE_ROOT + os.sep)

    class Notice(event.Listener):
        def on_start(self, ev) -> None:
            shown = _state['progress']
            if shown is not None and shown.running() or not ours(ev):
                return
            if not _state['noticed']:
                _state['noticed'] = True
                where = cache.state['notice_dir'] or '__pycache__ beside the modules'
                helped = bool(_state['expected']) and ahead.start_helper(_state['expected'])
                print(f'{cache.PACKAGE}: compiling numba kernels for first use (about '
                      f'{_COLD_COMPILE}{", in two processes" if helped else ""}, cached in '
                      f'{where})', file=sys.stderr, flush=True)
            if progress.wanted():
                plan = ahead.load_plan(_state['expected']) if _state['expected'] else None
                shown = progress.CompileProgress(progress.plan_costs(plan),
                                                 lambda: _holding['depth'] > 0)
                _state['progress'] = shown
                ahead.ready_hook = shown.compiled
                shown.start()

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


def _unique_function_names() -> None:
    """Number this process's compiled functions apart from any other process's.

    numba names a compiled function by its module, qualified name, argument types and a
    number it counts from 1 in each process: unique within a process only. Two functions of
    one module with one qualified name (two lambdas, two closures of one factory), each
    compiled first in a process of its own, can so get one name. A caller that links both
    from the cache (inner kernels' IR, numba's own linkable bitcode) keeps one body under
    that name (``linkonce_odr``) and runs it for both: the heap forms of ``arena.empty_i``
    and ``arena.empty_b`` made one-byte arrays where eight-byte ones were written, and the
    process died of a corrupted heap. Counting from a random 48-bit start, two processes'
    numbers meet with a chance of about n / 2**47 for n functions compiled; a forked child
    (``multiprocessing``'s default on Linux) draws a start of its own, or it would count on
    from its parent's number as its siblings do. Builds on numba internals
    (``FunctionIdentity._unique_ids``): AttributeError if they moved."""
    from numba.core import bytecode

    identity = bytecode.FunctionIdentity
    identity._unique_ids  # noqa: B018 (AttributeError if it moved)
    if getattr(identity, '_feeder_sim_ids', False):
        return

    def draw() -> None:
        identity._unique_ids = itertools.count(secrets.randbits(48) + 1)

    draw()
    identity._feeder_sim_ids = True
    os.register_at_fork(after_in_child=draw)


def _switch(name: str, off_means: str) -> bool:
    """An on/off environment variable, on unless it is 0; anything but 0 or 1 gets one line."""
    value = os.environ.get(name, '1').strip() or '1'
    if value not in ('0', '1'):
        print(f'{cache.PACKAGE}: {name}={value!r} is neither 0 nor 1; taken as 1 (set it to 0 '
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
    an owner, whose count is never touched (the arenas' arrays, :func:`.arena.borrow`). Such
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
            cache.warn(f'reference-count calls left as numba makes them (slower small steps): '
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
        _unique_function_names()
        # without unique names, linking a callee's IR from the cache may take another body
        if _switch(DEFER_ENV_VAR, 'to give every kernel machine code of its own'):
            _defer_codegen()
            cache.state['deferred_codegen'] = True
    except (ImportError, AttributeError):
        pass  # callee-only kernels get machine code of their own: a slower first compile
    try:
        if _switch(INLINE_ENV_VAR, 'to keep numba\'s out-of-line reference counting'):
            _inline_refcounts()
            cache.state['inline_refcounts'] = True
    except (ImportError, AttributeError):
        pass  # numba's out-of-line reference counting: slower small steps
    cache.state['installed'] = True   # what the key hashes is known
    try:
        ahead.install_locks()
    except (ImportError, AttributeError):
        pass  # two processes may compile a kernel at once: twice the work, the same code
    try:
        from numba.core import caching
        impl = getattr(caching, 'CacheImpl', None) or caching._CacheImpl
        locators = impl._locator_classes
        base = caching._CacheLocator
    except (ImportError, AttributeError) as e:
        cache.warn(f'numba {numba.__version__} has no cache locator hook ({e}); kernels are '
                   'cached beside their modules')
        return False
    if not any(getattr(c, '_feeder_sim_root', None) == cache.PACKAGE_ROOT for c in locators):
        locator = cache.make_locator(base)
        locator._feeder_sim_root = cache.PACKAGE_ROOT
        locators.insert(0, locator)
    return True


# Before any kernel is decorated: numba picks a function's cache locator at decoration time.
install()
