"""Scene files: where shipped scenes are found (:func:`scene_dirs`), reading a file's YAML
within size, nesting and alias limits, and :func:`load_scene`.

YAML is read with a safe loader that differs from ``yaml.safe_load`` in two ways, both aimed at
hand-written files: floats follow YAML 1.2 (``1e-3`` is a number, not the text "1e-3"), and a key
repeated in one mapping is an error instead of silently keeping the last value.
"""

from __future__ import annotations

from collections.abc import Mapping
import os
from pathlib import Path
import re
import sys
from typing import Any

import yaml

from feeder_sim.model.scene.errors import SceneError
from feeder_sim.model.scene.parse import parse_scene
from feeder_sim.model.scene.specs import MAX_FILE_BYTES, MAX_NESTING, MAX_VALUES, Scene


class _DuplicateKey(yaml.MarkedYAMLError):
    pass


class _NoDuplicateKeys:
    """A mapping whose key appears twice is an error (PyYAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == 'tag:yaml.org,2002:merge':
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node.start_mark)
            except TypeError:
                continue   # unhashable key: the base class reports it
            if first is not key_node.start_mark:
                err = _DuplicateKey('while reading a mapping', node.start_mark,
                                    f'duplicate key {key!r}', key_node.start_mark)
                err.first_line = first.line + 1
                raise err
        return super().construct_mapping(node, deep)


# PyYAML follows YAML 1.1, where 1e-3 (no dot) and 1.0e3 (unsigned exponent) are text.
_FLOAT_12 = re.compile(r'''^(?:
      [-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+
    | [-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
    )$''', re.VERBOSE)


class _SceneLoader(_NoDuplicateKeys, yaml.SafeLoader):
    """SafeLoader with YAML 1.2 floats and an error on duplicate keys."""


class _FastSceneLoader(_NoDuplicateKeys, getattr(yaml, 'CSafeLoader', yaml.SafeLoader)):
    """_SceneLoader on libyaml's parser where PyYAML has it: it parses in C what SafeLoader
    parses in Python, which shows on a scene of thousands of parts. A file it refuses is read
    again by _SceneLoader, whose messages and marks are the ones reported."""


for _loader in (_SceneLoader, _FastSceneLoader):
    _loader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_12,
                                  list('-+0123456789.'))


def scene_dirs() -> list[Path]:
    """Existing directories searched for shipped scenes, in order.

    $FEEDER_SIM_CONFIG (a list separated by os.pathsep), <sys.prefix>/share/feeder_sim/config,
    <prefix>/share/feeder_sim/config for each prefix in $AMENT_PREFIX_PATH (a sourced colcon
    install), and the source tree's config/.
    """
    candidates = [Path(p).expanduser()
                  for p in os.environ.get('FEEDER_SIM_CONFIG', '').split(os.pathsep) if p]
    candidates.append(Path(sys.prefix) / 'share' / 'feeder_sim' / 'config')
    candidates += [Path(p) / 'share' / 'feeder_sim' / 'config'
                   for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    candidates.append(Path(__file__).resolve().parents[3] / 'config')
    found: list[Path] = []
    for d in candidates:
        if d.is_dir() and d.resolve() not in {f.resolve() for f in found}:
            found.append(d)
    return found


def _is_ros_params(data) -> bool:
    return isinstance(data, Mapping) and any(
        isinstance(v, Mapping) and 'ros__parameters' in v for v in data.values())


def shipped_scenes() -> list[str]:
    """Names of the scenes in :func:`scene_dirs` (``*.yaml`` files, minus ROS parameter files)."""
    names = set()
    for d in scene_dirs():
        for f in d.glob('*.yaml'):
            try:
                data = read_yaml(f)
            except SceneError:
                data = None   # listed anyway, so that loading it shows the problem
            if not _is_ros_params(data):
                names.add(f.stem)
    return sorted(names)


def _find(path_or_name: str | os.PathLike) -> Path:
    given = os.fspath(path_or_name)
    if not str(given).strip():
        raise SceneError('no scene given: name a scene file or a shipped scene ('
                         f'{", ".join(shipped_scenes()) or "none found"})', source='<scene>')
    path = Path(given)
    if path.is_file():
        return path
    if path.is_dir():
        raise SceneError(f'{path.resolve()} is a directory; expected a .yaml scene file',
                         source=given)
    tried = [str(path.resolve())]
    looks_like_name = os.sep not in given and (os.altsep is None or os.altsep not in given)
    if looks_like_name:
        file_name = given if path.suffix in ('.yaml', '.yml') else f'{given}.yaml'
        for d in scene_dirs():
            candidate = d / file_name
            if candidate.is_file():
                return candidate
            tried.append(str(candidate))
    shipped = shipped_scenes()
    raise SceneError(f'scene not found; looked for {", ".join(tried)}. Give the path of a .yaml '
                     'file or the name of a shipped scene '
                     f'({", ".join(shipped) if shipped else "none found"}); '
                     'set FEEDER_SIM_CONFIG to add a scene directory', source=given)


def _check_nesting(data: Any, source: str) -> None:
    """Refuse data nested deeper than MAX_NESTING, expanding to more than MAX_VALUES values or
    holding itself. YAML aliases share one object among every place that names it, so a
    file of a few hundred bytes can stand for billions of values (ten levels of nine
    aliases): each object is visited once, iteratively, and its expanded size and depth are
    summed from its children's."""
    done: dict[int, tuple[int, int] | None] = {}     # id -> (values, depth); None: open
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        item, closing = stack.pop()
        if not isinstance(item, (dict, list)):
            continue
        kids = [c for c in (item.values() if isinstance(item, dict) else item)
                if isinstance(c, (dict, list))]
        if not closing:
            if id(item) in done:
                continue
            done[id(item)] = None
            stack.append((item, True))
            for kid in kids:
                if id(kid) in done and done[id(kid)] is None:
                    raise SceneError('a YAML alias refers to a mapping or list that contains '
                                     'it; write the repeated part out', source=source)
                stack.append((kid, False))
            continue
        sizes = [done[id(kid)] for kid in kids]
        values = len(item) + sum(v for v, _ in sizes)
        depth = 1 + max((d for _, d in sizes), default=0)
        if depth > MAX_NESTING:
            raise SceneError(f'nested deeper than {MAX_NESTING} levels; a scene file needs '
                             'about 6', source=source)
        if values > MAX_VALUES:
            raise SceneError(f'its YAML aliases expand to more than {MAX_VALUES} values; a '
                             'scene file needs some thousands: write repeated parts out or '
                             'name fewer aliases', source=source)
        done[id(item)] = (values, depth)


def read_yaml(path: Path, source: str | None = None) -> Any:
    """The plain data of a YAML file as scene files are read (module docstring: YAML 1.2
    floats, no duplicate keys), within MAX_FILE_BYTES, MAX_NESTING and MAX_VALUES; any
    problem is one SceneError naming ``source`` (default: the path) and the fix."""
    source = str(path) if source is None else source
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise SceneError(f'the file is {size / 2 ** 20:.1f} MiB; scene files are limited to '
                             f'{MAX_FILE_BYTES / 2 ** 20:.0f} MiB (a scene of thousands of parts '
                             'is well under one)', source=source)
        text = path.read_text(encoding='utf-8')
    except UnicodeDecodeError as err:
        raise SceneError(f'not UTF-8 text ({err.reason} at byte {err.start}); save the file as '
                         'UTF-8', source=source) from None
    except OSError as err:
        raise SceneError(f'cannot read the file: {err.strerror}', source=source) from None
    try:
        try:
            data = yaml.load(text, Loader=_FastSceneLoader)
        except yaml.YAMLError:
            data = yaml.load(text, Loader=_SceneLoader)
        _check_nesting(data, source)
    except RecursionError:
        raise SceneError(f'nested deeper than {MAX_NESTING} levels; a scene file needs about 6',
                         source=source) from None
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        line, column = (mark.line + 1, mark.column + 1) if mark else (None, None)
        where = f' at line {line}, column {column}' if mark else ''
        if isinstance(err, _DuplicateKey):
            raise SceneError(f'{err.problem}{where} (first given at line {err.first_line}); '
                             'each key may appear only once', source=source, line=line,
                             column=column) from None
        problem = err.problem or str(err)
        hint = ('; YAML indentation must use spaces, not tabs' if '\\t' in problem
                else '; check the indentation, colons and brackets there')
        raise SceneError(f'YAML syntax error{where}: {problem}{hint}', source=source,
                         line=line, column=column) from None
    except yaml.YAMLError as err:
        raise SceneError(f'YAML error: {err}', source=source) from None
    return data


def load_scene(path_or_name: str | os.PathLike,
               parameters: Mapping[str, float] | None = None) -> Scene:
    """Load and validate a scene file, given its path or the name of a shipped scene (and the
    values of its named parameters where not the defaults)."""
    data, source = read_scene_data(path_or_name)
    return parse_scene(data, source, parameters)


def read_scene_data(path_or_name: str | os.PathLike) -> tuple[Any, str]:
    """The plain data of a scene file (not yet validated) and its path, for tools that edit a
    scene before :func:`parse_scene` checks it; raises SceneError for what no reader takes."""
    path = _find(path_or_name)
    source = str(path)
    data = read_yaml(path, source)
    if data is None:
        raise SceneError('the file is empty; expected a mapping with at least `bodies`',
                         source=source)
    return data, source
