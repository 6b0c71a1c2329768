"""Where feeder_sim's compiled kernels are cached: one directory per key of the kernel sources.

``cache=True`` (:data:`.jit.JIT_OPTIONS`): compiled code is kept on disk, so only the first run
pays for compilation (a minute or more). numba's own scheme keys each file's cache on that file
alone, in ``__pycache__`` beside it, which fails three ways: an install elsewhere (colcon's
``install/``, another venv) compiles everything again; a kernel that calls a kernel of another
file keeps the old callee's machine code after that file changes; and cache entries still name
a module after it is renamed, so loading them fails. Here the whole set is keyed instead on a
hash of the package's kernel sources (see :func:`key_material`) with the Python, numba and
numpy versions, and kept in a per-user directory with one subdirectory per key:
$FEEDER_SIM_CACHE_DIR, else $NUMBA_CACHE_DIR/feeder_sim (numba's own override is honoured),
else $XDG_CACHE_HOME/feeder_sim or ~/.cache/feeder_sim. Any kernel change anywhere starts a
fresh set; the same sources at another path reuse it; the few most recently used sets are kept.
The scheme is a cache locator (:func:`make_locator`) that :func:`.jit.install` puts in front of
numba's own (a private numba interface): a numba without it gets plain ``cache=True`` and one
warning line.

Everything here applies to files under :data:`PACKAGE_ROOT` only; other numba code in the
process keeps numba's own locators. This module imports nothing else of feeder_sim.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
from pathlib import Path
import re
import shutil
import sys

import numba
import numpy as np

ENV_VAR = 'FEEDER_SIM_CACHE_DIR'
# the feeder_sim package directory (this module's is compiled/, inside it)
PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.basename(PACKAGE_ROOT)
# The decorators every kernel module imports, relative to the package; with this module, the
# machinery whose whole source is in the key (the options and patches that shape the machine
# code and the form of cache entries; the key and the layout of the cache).
JIT_MODULE = os.path.join('compiled', 'jit.py')
MACHINERY = (JIT_MODULE, os.path.join('compiled', 'cache.py'))

# Key directories kept besides the current one: a few for switching branches or installs,
# not one per edit of a kernel (a full set is some tens of MB).
_KEEP = 4
_KEY_DIR = re.compile(r'^[\w.-]+-numba[\w.+]+-[0-9a-f]{16}$')
_LAST_USED = '.last_used'
# A module-level import line that may be of the jit module, in any form (``from
# feeder_sim.compiled.jit import jit``, ``from feeder_sim.compiled import jit as _jit``, ``import
# feeder_sim.compiled.jit``, ``from .jit import inner``, ``from feeder_sim.compiled import (``):
# a module is parsed only if it has one, and its imports then decide (:func:`_package_imports`).
_MAY_IMPORT_JIT = re.compile(r'^(?:from|import)\s.*\b(?:jit|compiled)\b', re.M)

# What the key and the notice need to know. deferred_codegen, inline_refcounts: whether the
# patches of :mod:`.jit` are on (the key hashes them), set by :func:`.jit.install`, which then
# sets installed: no key directory is taken before (it would be another key's); notice_dir: the
# key directory kernels were routed to; warned: one line said.
state = {'notice_dir': None, 'warned': False, 'deferred_codegen': False,
         'inline_refcounts': False, 'installed': False}


def warn(message: str) -> None:
    """One line on stderr, the first time only (every fallback of the cache and the patches)."""
    if not state['warned']:
        state['warned'] = True
        print(f'{PACKAGE}: {message}', file=sys.stderr, flush=True)


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

    The full source of every kernel module (one importing :mod:`.jit`, in any form: the
    arenas' :mod:`.arena` too) and of the machinery (:data:`MACHINERY`: :mod:`.jit` and this
    module); the module-level assignments that kernel modules import from other modules of the
    package (numba freezes globals into the machine code); and where each NamedTuple class of
    the package is defined (the cache index records argument types by module and name, so a
    moved class would make numba fail to read the index)."""
    jit_file = os.path.join(root, JIT_MODULE)
    machinery = {os.path.join(root, rel) for rel in MACHINERY}
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
        if path not in machinery and _MAY_IMPORT_JIT.search(source):
            trees[path] = ast.parse(source, path)
            imports[path] = _package_imports(root, rel, trees[path])
        material += [(rel, f'NamedTuple {m}')
                     for m in re.findall(r'^class (\w+)\(\s*(?:typing\.)?NamedTuple\b', source,
                                         re.M)]
    kernels = {path for path, found in imports.items() if any(f == jit_file for f, _ in found)}
    kernels |= machinery & sources.keys()
    for path in sorted(kernels):
        material.append((os.path.relpath(path, root), sources[path]))
    for path in sorted(kernels - machinery):
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
                 numba.__version__, np.__version__, str(state['deferred_codegen']),
                 str(state['inline_refcounts'])):
        h.update(part.encode() + b'\0')
    for rel, text in key_material(root):
        h.update(rel.replace(os.sep, '/').encode() + b'\0' + text.encode() + b'\0')
    return f'{sys.implementation.cache_tag}-numba{numba.__version__}-{h.hexdigest()[:16]}'


def key_dir() -> Path:
    """This package's key directory; marks it used, and makes room if it is new.

    Raises OSError (unwritable, unreadable) or SyntaxError (a module being edited); and
    RuntimeError in a process that has not imported :mod:`.jit` yet (whose ``install`` sets
    what the key hashes)."""
    if not state['installed']:
        raise RuntimeError(f'{PACKAGE}: the kernel cache was asked for its key directory before '
                           'feeder_sim.compiled.jit was imported')
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


def make_locator(base: type) -> type:
    """The cache locator class, a subclass of numba's ``_CacheLocator`` ``base``."""

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
                warn(f'no kernel cache in {cache_root()} ({e}); numba caches beside the '
                     'modules instead')
                return None  # numba's own locators are next in line
            state['notice_dir'] = key_dir()
            return self

    return PackageLocator
