"""Checkers of one value each (number, list of numbers, text, choice, mapping of known keys):
each takes (value, key path) and returns the clean value or raises ``_Invalid``."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
import difflib
import math
from numbers import Real
import re
from typing import Any

import numpy as np

from feeder_sim.model.checks import is_number
from feeder_sim.model.scene.errors import _describe, _Invalid, _is_list
from feeder_sim.model.scene.expressions import _evaluate, _PARAMETER_VALUES


def _join(path: str, key: str) -> str:
    return f'{path}.{key}' if path else key


def _suggest(word: str, choices) -> str:
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ''


def _range_text(lo, hi, lo_open, hi_open) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"{'<' if hi_open else '<='} {hi:g}"


def _number(value, path: str, lo: float | None = None, hi: float | None = None, *,
            lo_open: bool = False, hi_open: bool = False, unit: str = '', hint: str = '') -> float:
    """A finite real number (bool is not a number), optionally within [lo, hi] (or open ends).

    In a scene with ``parameters``, text that is not a number is an expression of them."""
    names = _PARAMETER_VALUES.get()
    if names is not None and isinstance(value, str) and not _looks_numeric(value):
        value = _evaluate(value, path, names)
    expected = 'a number' + (f' ({unit})' if unit else '')
    if lo is not None or hi is not None:
        expected += ' ' + _range_text(lo, hi, lo_open, hi_open)
    if not is_number(value):
        extra = ''
        if isinstance(value, str) and _looks_numeric(value):
            extra = '; YAML read it as text: remove any quotes'
            if _yaml11_number(value) != value.strip():
                extra += f' (and write it as {_yaml11_number(value)} for YAML 1.1 readers)'
        raise _Invalid(path, f'expected {expected}, got {_describe(value)}{extra}')
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise _Invalid(path, f'expected {expected}, got {x!r}; only finite numbers are allowed')
    below = lo is not None and (x <= lo if lo_open else x < lo)
    above = hi is not None and (x >= hi if hi_open else x > hi)
    if below or above:
        raise _Invalid(path, f'{x:g} is out of range; expected {expected}'
                       + (f'; {hint}' if hint else ''))
    return x



def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _yaml11_number(text: str) -> str:
    # YAML 1.1 (PyYAML's safe_load) needs a dot in the mantissa and a sign in the exponent.
    mantissa, _, exponent = text.strip().lower().partition('e')
    if '.' not in mantissa:
        mantissa += '.0'
    if exponent and exponent[0] not in '+-':
        exponent = '+' + exponent
    return f'{mantissa}e{exponent}' if exponent else mantissa


def _vec(value, path: str, n: int, what: str = '',
         limits: tuple[float, ...] | None = None) -> np.ndarray:
    """A list of exactly n finite numbers, each within +-limits[k] if given."""
    shape = f'{n} numbers' + (f' {what}' if what else '')
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of {shape}, got {_describe(value)}')
    if len(value) != n:
        raise _Invalid(path, f'expected {shape}, got {_describe(value)}')
    if limits is None:
        return np.array([_number(x, f'{path}[{k}]') for k, x in enumerate(value)])
    return np.array([_number(x, f'{path}[{k}]', -lim, lim,
                             hint='larger values do not keep a run finite and meaningful')
                     for k, (x, lim) in enumerate(zip(value, limits, strict=True))])


def _string(value, path: str) -> str:
    if not isinstance(value, str):
        quote = '; put it in quotes' if isinstance(value, (Real, bool)) else ''
        raise _Invalid(path, f'expected text, got {_describe(value)}{quote}')
    if not value.strip():
        raise _Invalid(path, 'expected non-empty text')
    return value


def _choice(value, path: str, choices: tuple[str, ...]) -> str:
    options = ', '.join(choices)
    if not isinstance(value, str):
        raise _Invalid(path, f'expected one of {options}, got {_describe(value)}')
    if value not in choices:
        raise _Invalid(path, f'unknown value {value!r}{_suggest(value, choices)}; '
                             f'expected one of {options}')
    return value


def _boolean(value, path: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise _Invalid(path, f'expected true or false, got {_describe(value)}')
    return bool(value)


# Common misnamings that difflib cannot guess (too short or a different word).
_ALIASES = {
    'mu': 'mu_static', 'friction': 'mu_static', 'mu_s': 'mu_static', 'mu_d': 'mu_dynamic',
    'mu_k': 'mu_dynamic', 'mu_kinetic': 'mu_dynamic', 'e': 'restitution', 'cor': 'restitution',
    'vertices': 'polygon', 'shape': 'polygon', 'position': 'pose', 'vel': 'velocity',
    'dt': 'time_step', 'h': 'time_step', 'rtol': 'tolerance', 'freq': 'frequency',
    'f': 'frequency', 'a': 'amplitude', 'amp': 'amplitude', 'direction': 'angle', 'g': 'gravity',
    'kind': 'type', 'body': 'bodies', 'parts': 'bodies',
}


def _mapping(value, path: str, allowed) -> Mapping:
    """A mapping with text keys drawn from ``allowed``."""
    if not isinstance(value, Mapping):
        where = 'the top level of the file to be ' if not path else ''
        raise _Invalid(path, f'expected {where}a mapping with the keys {", ".join(allowed)}; '
                             f'got {_describe(value)}')
    for key in value:
        if not isinstance(key, str):
            raise _Invalid(path, f'keys must be text, got the key {_describe(key)}; '
                                 f'allowed keys: {", ".join(allowed)}')
        if key not in allowed:
            guess = _suggest(key, allowed)
            if not guess and _ALIASES.get(key) in allowed:
                guess = f" (did you mean '{_ALIASES[key]}'?)"
            raise _Invalid(_join(path, key), f'unknown key {key!r}{guess}; '
                                             f'allowed keys: {", ".join(allowed)}')
    return value


_REQUIRED = object()   # the key must be present
_AUTO = object()       # absent: the value is worked out later from the rest of the scene


@dataclass(frozen=True)
class _Field:
    check: Callable[[Any, str], Any]
    expected: str                     # shown when the key is missing or null
    default: Any = _REQUIRED
    nullable: bool = False            # pass null to ``check`` instead of rejecting it


def _fields(value, path: str, table: Mapping[str, _Field]) -> dict[str, Any]:
    """Check a mapping against a table of fields; returns every field, defaults filled in."""
    data = _mapping(value, path, table)
    out = {}
    for key, spec in table.items():
        sub = _join(path, key)
        if key not in data:
            if spec.default is _REQUIRED:
                raise _Invalid(sub, f'missing required key {key!r}; expected {spec.expected}')
            out[key] = spec.default
        elif data[key] is None and not spec.nullable:
            raise _Invalid(sub, f'{key!r} has no value; expected {spec.expected}')
        else:
            out[key] = spec.check(data[key], sub)
    return out


def _num(lo=None, hi=None, **kw) -> Callable[[Any, str], float]:
    return lambda value, path: _number(value, path, lo, hi, **kw)



def _whole(value, path: str, lo: int, hi: int) -> int:
    x = _number(value, path, lo, hi)
    if x != int(x):
        raise _Invalid(path, f'expected a whole number in [{lo}, {hi}], got {x!r}')
    return int(x)


def _name_matching(pattern: re.Pattern, refusal: str):
    """A checker of names that ``pattern`` matches, refusing others with ``refusal``."""
    def check(value, path: str) -> str:
        name = _string(value, path)
        if not pattern.match(name):
            raise _Invalid(path, f'{name!r} {refusal}')
        return name
    return check
