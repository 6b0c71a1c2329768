"""What an invalid scene raises: :class:`SceneError` for callers, ``_Invalid`` inside the
checkers, and how their messages name the value they found (``_describe``)."""

from __future__ import annotations

from collections.abc import Mapping
from numbers import Real

import numpy as np


class SceneError(ValueError):
    """An invalid scene, with the offending key path and the file it came from.

    ``path`` is like ``'bodies[2].polygon'`` ('' for the file as a whole), ``source`` the file name
    (or ``'<dict>'``), ``message`` the bare explanation; ``line``/``column`` (1-based) are set for
    YAML syntax errors.
    """

    def __init__(self, message: str, path: str = '', source: str = '<dict>',
                 line: int | None = None, column: int | None = None):
        self.message = message
        self.path = path
        self.source = source
        self.line = line
        self.column = column
        super().__init__(': '.join(part for part in (source, path, message) if part))

    def __reduce__(self):
        return (SceneError, (self.message, self.path, self.source, self.line, self.column))


class _Invalid(Exception):
    """Raised by the checkers; parse_scene adds the source and turns it into a SceneError."""

    def __init__(self, path: str, message: str):
        super().__init__(path, message)
        self.path = path
        self.message = message


def _is_list(value) -> bool:
    return isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim > 0)


def _describe(value) -> str:
    if value is None:
        return 'nothing (null)'
    if isinstance(value, (bool, np.bool_)):
        return f'{str(bool(value)).lower()} (a boolean)'
    if isinstance(value, str):
        return f'the text {value!r}'
    if isinstance(value, Mapping):
        return 'a mapping'
    if _is_list(value):
        return f'a list of {len(value)} item' + ('' if len(value) == 1 else 's')
    if isinstance(value, Real):
        return f'{value!r}'
    return f'a {type(value).__name__}'
