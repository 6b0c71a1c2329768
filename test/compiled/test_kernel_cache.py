"""The compiled-kernel cache: keyed on the kernel sources, shared by copies at any path, announced.

Each run is a fresh interpreter on a copy of the package (plus a two-file probe: a kernel
calling a kernel of another module) with its own cache directory, so nothing here reads or
writes the caches of the source tree or of the user.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import textwrap

import pytest

from feeder_sim.compiled import cache as kernel_cache
from feeder_sim.compiled import jit as compiled_jit

PACKAGE = Path(kernel_cache.PACKAGE_ROOT)
NOTICE = 'compiling numba kernels for first use'
# a kernel module's import of the decorators, as the package writes it
JIT_IMPORT = re.compile(r'^from feeder_sim\.compiled(?:\.jit import | import .*\bjit\b)', re.M)

CALLEE = '''
from feeder_sim.compiled.jit import inner


@inner
def scale(x):
    return {factor} * x
'''

# the module form of the import (the callee's is the names' form): both are kernel modules
CALLER = '''
from feeder_sim._probe.callee import scale
from feeder_sim.compiled import jit as _jit


@_jit.jit
def probe(x):
    return scale(x) + 1.0
'''

RUN = '''
import json
from feeder_sim.compiled import cache
from feeder_sim._probe.caller import probe
value = probe(3.0)
print(json.dumps({'value': value, 'hits': sum(probe.stats.cache_hits.values()),
                  'misses': sum(probe.stats.cache_misses.values()),
                  'cache_path': probe.stats.cache_path, 'key_dir': str(cache._key_dir()),
                  'file': cache.__file__}))
'''

# a kernel new to the cache, compiled against the callee's cache entry (its IR)
NEW_CALLER = '''
import json
import numba
from feeder_sim._probe.callee import scale


@numba.njit
def fresh(x):
    return scale(x) - 1.0


print(json.dumps({'value': fresh(3.0), 'callee_hits': sum(scale.stats.cache_hits.values()),
                  'callee_misses': sum(scale.stats.cache_misses.values())}))
'''


def copy_package(dest: Path, factor: int = 2) -> Path:
    """A copy of the package with the probe at ``dest/feeder_sim``; returns ``dest``."""
    shutil.copytree(PACKAGE, dest / 'feeder_sim',
                    ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
    probe = dest / 'feeder_sim' / '_probe'
    probe.mkdir()
    (probe / '__init__.py').write_text('')
    (probe / 'callee.py').write_text(CALLEE.format(factor=factor))
    (probe / 'caller.py').write_text(CALLER)
    return dest


def probe_env(tree: Path, cache: Path) -> dict:
    """This process's environment for a run of ``tree``'s package on the kernel cache
    ``cache``, without the caller's numba and feeder_sim settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(('NUMBA_', 'FEEDER_SIM'))}
    env.update(PYTHONPATH=str(tree), FEEDER_SIM_CACHE_DIR=str(cache))
    return env


def run(tree: Path, cache: Path, code: str = RUN,
        extra_env: dict | None = None) -> tuple[dict | None, str]:
    env = {**probe_env(tree, cache), **(extra_env or {})}
    # cwd: not the source tree, whose feeder_sim would shadow the copy
    proc = subprocess.run([sys.executable, '-c', code], cwd=tree, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.strip().splitlines()
    return (json.loads(out[-1]) if out else None), proc.stderr


def test_cold_warm_relocated_and_a_changed_callee(tmp_path):
    cache = tmp_path / 'cache'
    first = copy_package(tmp_path / 'first')
    # Key directories of earlier sources, least recently used first; and a file of the user's.
    old = [cache / f'cpython-311-numba0.1-{i:016x}' for i in range(6)]
    for i, d in enumerate(old):
        d.mkdir(parents=True)
        (d / '.last_used').touch()
        os.utime(d / '.last_used', (1e9 + i, 1e9 + i))
    (cache / 'notes').mkdir()

    cold, err = run(first, cache)
    assert cold['file'].startswith(str(first))
    assert (cold['value'], cold['hits'], cold['misses']) == (7.0, 0, 1)
    key_dir = Path(cold['key_dir'])
    assert key_dir.parent == cache
    assert key_dir.name == kernel_cache.cache_key(str(first / 'feeder_sim'))
    # the module's folder mirrored under the key: two modules of one name cannot clash
    assert Path(cold['cache_path']) == key_dir / '_probe'
    assert sorted(p.name.split('-')[0] for p in key_dir.glob('_probe/*.nbi')) == \
        ['callee.scale', 'caller.probe']
    notices = [line for line in err.splitlines() if NOTICE in line]
    assert len(notices) == 1, err
    where = re.escape(str(key_dir))
    assert re.fullmatch(rf'feeder_sim: {NOTICE} \(about .+ s, cached in {where}\)', notices[0])
    assert sorted(p.name for p in cache.iterdir()) == sorted(
        [key_dir.name, 'notes'] + [d.name for d in old[-kernel_cache._KEEP:]])

    warm, err = run(first, cache)
    assert (warm['value'], warm['hits'], warm['misses']) == (7.0, 1, 0)
    assert NOTICE not in err
    fresh, _ = run(first, cache, NEW_CALLER)
    assert fresh == {'value': 5.0, 'callee_hits': 1, 'callee_misses': 0}

    # the same sources at another path: same key, loaded without compiling
    moved = tmp_path / 'moved'
    shutil.copytree(first, moved)
    shutil.rmtree(first)
    relocated, err = run(moved, cache)
    assert relocated['file'].startswith(str(moved))
    assert relocated['key_dir'] == str(key_dir)
    assert (relocated['value'], relocated['hits'], relocated['misses']) == (7.0, 1, 0)
    assert NOTICE not in err

    # only the callee changes, in its own file: the caller is not served stale machine code
    callee = moved / 'feeder_sim' / '_probe' / 'callee.py'
    callee.write_text(CALLEE.format(factor=3))
    changed, err = run(moved, cache)
    assert changed['key_dir'] != str(key_dir)
    assert (changed['value'], changed['hits'], changed['misses']) == (10.0, 0, 1)
    assert NOTICE in err


def edited(root: Path, rel: str, old: str, new: str) -> str:
    path = root / rel
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    try:
        return kernel_cache.cache_key(str(root))
    finally:
        path.write_text(text)


def test_the_key_follows_kernel_sources_and_their_constants_only(tmp_path):
    root = copy_package(tmp_path)
    shutil.rmtree(root / 'feeder_sim' / '_probe')
    root = root / 'feeder_sim'
    key = kernel_cache.cache_key(str(root))
    assert key == kernel_cache.cache_key(str(root))
    material = kernel_cache.key_material(str(root))
    kernel_modules = {rel for rel, text in material
                      if rel.endswith('.py') and JIT_IMPORT.search(text)}
    assert {'contact/_lcp_kernels.py', 'contact/_island_kernels.py',
            'stepping/time_stepping/_kernels.py', 'compiled/arena.py'} <= kernel_modules
    # the machinery's whole source: the options and patches, the key and the cache's layout
    assert {'compiled/jit.py', 'compiled/cache.py'} <= {rel for rel, _ in material}
    for rel in ('compiled/jit.py', 'compiled/cache.py'):
        assert edited(root, rel, '\n', '\n# edited\n') != key, rel
    # the helper and the progress lines make no machine code
    for rel in ('compiled/ahead.py', 'compiled/progress.py', 'compiled/__init__.py'):
        assert edited(root, rel, '\n', '\n# edited\n') == key, rel
    # any kernel module, anywhere in the package
    for rel in kernel_modules:
        assert edited(root, rel, '\n', '\n# edited\n') != key, rel
    # a constant that kernels import from a plain module is frozen into their machine code
    assert edited(root, 'model/world.py', 'FIXED, DRIVEN, MOVING = 0, 1, 2',
                  'FIXED, DRIVEN, MOVING = 0, 2, 1') != key
    # a module without kernels, and a comment beside those constants, leave the key alone
    assert edited(root, 'cli.py', '\n', '\n# edited\n') == key
    assert edited(root, 'model/world.py', 'FIXED, DRIVEN, MOVING = 0, 1, 2',
                  'FIXED, DRIVEN, MOVING = 0, 1, 2  # edited') == key
    # a renamed kernel module cannot be served entries that name the old module
    (root / 'contact' / '_lcp_kernels.py').rename(root / 'contact' / '_lcp_kernels2.py')
    assert kernel_cache.cache_key(str(root)) != key


@pytest.mark.parametrize('form', [
    'from feeder_sim.compiled.jit import jit',
    'from feeder_sim.compiled.jit import (\n    inner,\n    jit,\n)',
    'from feeder_sim.compiled import jit as _jit',
    'from feeder_sim.compiled import (\n    arena,\n    jit,\n)',
    'import feeder_sim.compiled.jit',
    'import feeder_sim.compiled.jit as _jit',
    'from .compiled import jit',
    'from .compiled.jit import jit'])
def test_a_kernel_module_is_one_importing_jit_in_any_form(tmp_path, form):
    root = copy_package(tmp_path)
    shutil.rmtree(root / 'feeder_sim' / '_probe')
    root = root / 'feeder_sim'
    (root / '_form.py').write_text(f'{form}\n\nX = 1\n')
    key = kernel_cache.cache_key(str(root))
    assert '_form.py' in {rel for rel, _ in kernel_cache.key_material(str(root))}
    assert edited(root, '_form.py', 'X = 1', 'X = 2') != key
    # an import of the cache alone, or of the arenas alone, makes no kernel module
    (root / '_form.py').write_text('from feeder_sim.compiled import arena, cache\n\nX = 1\n')
    assert '_form.py' not in {rel for rel, _ in kernel_cache.key_material(str(root))}


def test_no_key_directory_before_the_jit_module_sets_what_the_key_hashes(tmp_path):
    # the key hashes whether the patches are on, which importing compiled.jit decides; the
    # cache (which imports nothing of the package) would take another key before
    tree = copy_package(tmp_path / 'tree')
    code = ('import json\nfrom feeder_sim.compiled import cache\ntry:\n    cache.key_dir()\n'
            'except RuntimeError as e:\n    print(json.dumps(str(e)))\n')
    message, _ = run(tree, tmp_path / 'cache', code)
    assert message.endswith('before feeder_sim.compiled.jit was imported')
    assert not (tmp_path / 'cache').exists()


@pytest.mark.parametrize('case', ['numba without the internals', 'turned off'])
def test_without_deferred_codegen_callees_get_their_own_machine_code(tmp_path, case):
    tree = copy_package(tmp_path / 'tree')
    cache = tmp_path / 'cache'
    if case == 'turned off':
        code, env = RUN, {compiled_jit.DEFER_ENV_VAR: '0'}
    else:
        code, env = 'from numba.core import codegen\ndel codegen.JITCodeLibrary\n' + RUN, {}
    for hits in (0, 1):
        result, err = run(tree, cache, code, env)
        assert (result['value'], result['hits']) == (7.0, hits)
        assert [line for line in err.splitlines() if NOTICE not in line] == []
    assert sorted(p.name.split('-')[0] for p in Path(result['key_dir']).glob('_probe/*.nbi')) \
        == ['callee.scale', 'caller.probe']


@pytest.mark.parametrize('name, off_means', [
    (compiled_jit.DEFER_ENV_VAR, 'to give every kernel machine code of its own'),
    (compiled_jit.INLINE_ENV_VAR, "to keep numba's out-of-line reference counting")])
def test_a_switch_other_than_0_or_1_is_one_line_naming_it(tmp_path, name, off_means):
    tree = copy_package(tmp_path / 'tree')
    result, err = run(tree, tmp_path / 'cache', RUN, {name: 'false'})
    assert result['value'] == 7.0
    lines = [line for line in err.splitlines() if NOTICE not in line]
    assert lines == [f"feeder_sim: {name}='false' is neither 0 nor 1; taken as 1 "
                     f'(set it to 0 {off_means})']


# island_groups on heap arrays, 100 times: its islands, numba's own allocation counts, and
# its optimized module's calls of numba's reference counting and null tests before them
REFCOUNTS = '''
import json, re
import numpy as np
from numba.core.runtime import rtsys
from feeder_sim.compiled import cache, jit as compiled_jit
from feeder_sim.compiled.arena import heap_state
from feeder_sim.contact._island_kernels import island_groups

dynamic = np.array([False, True, True, True, True])
a, b = np.array([1, 2, 4, 3]), np.array([0, 1, 0, 0])
islands = [x.tolist() for x in island_groups(heap_state(), 5, dynamic, a, b)]
before = rtsys.get_allocation_stats()
for _ in range(100):
    out = island_groups(heap_state(), 5, dynamic, a, b)
del out
after = rtsys.get_allocation_stats()
ir = island_groups.inspect_llvm(island_groups.signatures[0])
print(json.dumps({'inlined': cache.state['inline_refcounts'], 'islands': islands,
                  'allocated': after.mi_alloc - before.mi_alloc,
                  'freed': after.mi_free - before.mi_free, 'key_dir': str(cache._key_dir()),
                  'tests': len(re.findall(r'%owned[.\\w]* = icmp ne ptr', ir)),
                  'calls': len(re.findall(r'call void @NRT_(?:incref|decref)\\(', ir))}))
'''


def test_reference_counts_inlined_or_not_balance_and_give_the_same_answer(tmp_path):
    tree = copy_package(tmp_path / 'tree')
    results = {}
    for inline in ('1', '0'):
        results[inline], _ = run(tree, tmp_path / 'cache', REFCOUNTS,
                                 {compiled_jit.INLINE_ENV_VAR: inline, 'NUMBA_NRT_STATS': '1'})
    on, off = results['1'], results['0']
    assert (on['inlined'], off['inlined']) == (True, False)
    # bodies 1 and 2 joined by a contact, 3 and 4 alone: (order, starts, bodies, body_starts)
    assert on['islands'] == off['islands'] == [[0, 1, 3, 2], [0, 2, 3, 4], [1, 2, 3, 4],
                                               [0, 2, 3, 4]]
    # every array made is freed once, no more: a count dropped or doubled would show here
    assert on['allocated'] == on['freed'] == off['allocated'] == off['freed'] > 0
    # the same counting calls left after numba's pruning, behind null tests or not
    assert on['calls'] == off['calls'] > 0
    assert on['tests'] > 0 == off['tests']
    assert on['key_dir'] != off['key_dir']


def test_null_tests_that_llvm_cannot_read_leave_numbas_calls_with_one_line(tmp_path):
    tree = copy_package(tmp_path / 'tree')
    imports = 'from feeder_sim.compiled import cache, jit as compiled_jit\n'
    code = REFCOUNTS.replace(imports, imports + 'compiled_jit._NRT_TESTED = "not IR {op}"\n')
    result, err = run(tree, tmp_path / 'cache', code, {'NUMBA_NRT_STATS': '1'})
    assert result['islands'] == [[0, 1, 3, 2], [0, 2, 3, 4], [1, 2, 3, 4], [0, 2, 3, 4]]
    assert result['allocated'] == result['freed'] > 0
    assert result['tests'] == 0
    lines = [line for line in err.splitlines() if NOTICE not in line]
    assert len(lines) == 1 and lines[0].startswith(
        'feeder_sim: reference-count calls left as numba makes them'), err


@pytest.mark.parametrize('case', ['numba without the hook', 'unwritable cache directory'])
def test_falls_back_to_numbas_own_cache_with_one_line(tmp_path, case):
    tree = copy_package(tmp_path / 'tree')
    cache = tmp_path / 'cache'
    code = RUN
    if case == 'numba without the hook':
        code = 'from numba.core import caching\ndel caching._CacheLocator\n' + code
    else:
        cache.write_text('a file where the cache directory should be')
    result, err = run(tree, cache, textwrap.dedent(code))
    assert result['value'] == 7.0
    lines = err.splitlines()
    assert len([line for line in lines if NOTICE not in line]) == 1, err
    assert lines[0].startswith('feeder_sim: ')
    assert Path(result['cache_path']) == tree / 'feeder_sim' / '_probe' / '__pycache__'


OTHER_NUMBA = '''
import ctypes, json
import numba
import numpy as np
from feeder_sim.compiled import cache
from feeder_sim._probe.callee import scale


@numba.vectorize(['float64(float64)'])
def twice(x):
    return 2.0 * x


@numba.njit(no_cpython_wrapper=True)
def plus_one(x):
    return x + 1.0


@numba.njit
def user(x):
    return plus_one(x) * scale(x)


@numba.cfunc('float64(float64)')
def as_c(x):
    return plus_one(x) * 3.0


@numba.njit
def call(f, x):
    return f(x)


library = plus_one.overloads[plus_one.signatures[0]].library
deferred = getattr(library, '_feeder_sim_deferred', False)
address = library.get_pointer_to_function(plus_one.overloads[plus_one.signatures[0]]
                                          .fndesc.llvm_func_name)
# numba's calling convention: status = f(&result, &exception info, arguments...)
native = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_double)(address)
out, excinfo = ctypes.c_double(), ctypes.c_void_p()
status = native(ctypes.addressof(out), ctypes.addressof(excinfo), 4.0)
print(json.dumps({'deferred': cache.state['deferred_codegen'], 'plus_one_deferred': deferred,
                  'twice': twice(np.arange(3.0)).tolist(), 'user': user(3.0),
                  'cfunc': as_c.ctypes(1.0), 'first_class': call(user, 1.0),
                  'asked_for': [status, out.value]}))
'''


def test_other_numba_code_in_the_process_and_code_asked_for_later(tmp_path):
    # what the deferral touches is every function without a Python wrapper in the process:
    # ufuncs, cfuncs, first-class functions of another package keep working, and a deferred
    # function's own machine code is made when something asks for it (here a pointer, called)
    tree = copy_package(tmp_path / 'tree')
    result, err = run(tree, tmp_path / 'cache', OTHER_NUMBA)
    assert result == {'deferred': True, 'plus_one_deferred': True, 'twice': [0.0, 2.0, 4.0],
                      'user': 24.0, 'cfunc': 6.0, 'first_class': 4.0, 'asked_for': [0, 5.0]}


def test_kernel_load_seconds_count_compiles_and_loads_not_calls():
    # what the node subtracts from a frame's wall time before it decides to slice frames: the
    # time in numba's compiler lock, which a first call holds and later calls do not
    import time

    import numba

    @numba.njit
    def hypot(x, y):
        return (x * x + y * y) ** 0.5

    before = compiled_jit.kernel_load_seconds()
    t0 = time.perf_counter()
    assert hypot(3.0, 4.0) == 5.0
    first_s = time.perf_counter() - t0
    loaded_s = compiled_jit.kernel_load_seconds() - before
    # the compile is nearly all of the first call (measured: 0.2 s of compile, 1 ms more)
    assert 0.5 * first_s < loaded_s <= first_s
    before = compiled_jit.kernel_load_seconds()
    for _ in range(100):
        hypot(3.0, 4.0)
    assert compiled_jit.kernel_load_seconds() == before


# Two functions of one module with one qualified name (two lambdas here; the heap forms of
# arena.empty_i and empty_b in the package), each called through an inner kernel: numba names
# a compiled function by module, qualified name, argument types and a number it counts in each
# process, so each compiled first in a process of its own got one name, and a caller linking
# both inner kernels' cache entries (their IR) one body for both calls (44.0 here; a corrupted
# heap in a study's workers).
TWINS = '''
from feeder_sim.compiled.jit import inner, jit

first = inner(lambda x: x + 1.0)
second = inner(lambda x: x * 2.0)


@inner
def via_first(x):
    return first(x)


@inner
def via_second(x):
    return second(x)


@jit
def run_first(x):
    return via_first(x)


@jit
def run_second(x):
    return via_second(x)


@jit
def run_both(x):
    return via_first(x) + 10.0 * via_second(x)
'''


# each kernel compiled in a child forked from one parent (multiprocessing's default on Linux)
FORKED = '''
import json
import multiprocessing
from feeder_sim._probe import twins


def call(name, queue):
    queue.put(getattr(twins, name)(3.0))


context = multiprocessing.get_context('fork')
queue = context.Queue()
values = []
for name in ('run_first', 'run_second'):
    child = context.Process(target=call, args=(name, queue))
    child.start()
    values.append(queue.get(timeout=60))
    child.join()
print(json.dumps(values))
'''


@pytest.mark.parametrize('how', ['processes', 'forked children'])
def test_functions_of_one_name_compiled_in_two_processes_keep_their_own_code(tmp_path, how):
    tree = copy_package(tmp_path / 'tree')
    (tree / 'feeder_sim' / '_probe' / 'twins.py').write_text(TWINS)
    cache = tmp_path / 'cache'
    call = ('import json\nfrom feeder_sim._probe import twins\n'
            'print(json.dumps(twins.{}(3.0)))\n')
    if how == 'processes':
        assert run(tree, cache, call.format('run_first'))[0] == 4.0
        assert run(tree, cache, call.format('run_second'))[0] == 6.0
    else:
        assert run(tree, cache, FORKED)[0] == [4.0, 6.0]
    # both inner kernels from the cache, linked into a new caller: 4 + 10 * 6
    assert run(tree, cache, call.format('run_both'))[0] == 64.0
