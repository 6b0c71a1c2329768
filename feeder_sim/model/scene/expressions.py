"""Numbers written as expressions of a scene's named ``parameters`` (simpleeval: arithmetic
and the functions of :data:`EXPRESSION_FUNCTIONS`, nothing else)."""

from __future__ import annotations

import ast
from collections.abc import Mapping
from contextvars import ContextVar
import math

import simpleeval

from feeder_sim.model.checks import is_number
from feeder_sim.model.scene.errors import _describe, _Invalid

# The values of the scene's parameters while its numbers are checked (None: it has none).
_PARAMETER_VALUES: ContextVar[dict[str, float] | None] = ContextVar('parameters', default=None)
EXPRESSION_FUNCTIONS = {name: getattr(math, name) for name in (
    'sin', 'cos', 'tan', 'asin', 'acos', 'atan', 'atan2', 'sqrt', 'exp', 'log', 'hypot',
    'radians', 'degrees', 'floor', 'ceil')} | {'abs': abs, 'min': min, 'max': max}
EXPRESSION_CONSTANTS = {'pi': math.pi, 'g': 9.81}


# An expression's length: a formula of a few parameters is tens of characters; Python's
# parser recurses per nesting level and runs out of stack (or memory) on ~100 000.
MAX_EXPRESSION_CHARS = 1000


def _evaluate(text: str, path: str, values: Mapping[str, float]) -> float:
    """A number from an expression of the scene's parameters (simpleeval: arithmetic, the
    functions above, no attribute access, no calls of anything else)."""
    if len(text) > MAX_EXPRESSION_CHARS:
        raise _Invalid(path, f'an expression of {len(text)} characters ({text[:40]!r}...); '
                             f'expressions are limited to {MAX_EXPRESSION_CHARS}: name a '
                             'parameter for the repeated part')
    evaluator = simpleeval.SimpleEval(names={**EXPRESSION_CONSTANTS, **values},
                                      functions=EXPRESSION_FUNCTIONS)
    try:
        _refuse_truth_values(text, path)
        result = evaluator.eval(text)
    except (RecursionError, MemoryError):
        raise _Invalid(path, f'{text[:40]!r}... is nested too deeply to evaluate; write it '
                             'with fewer parentheses or signs') from None
    except (simpleeval.InvalidExpression, SyntaxError, ArithmeticError, TypeError,
            ValueError) as err:
        known = ', '.join(sorted(values)) or 'none'
        reason = getattr(err, 'message', None) or str(err) or type(err).__name__
        raise _Invalid(path, f'cannot evaluate {text!r}: {reason}; parameters: {known}; '
                             'functions: ' + ', '.join(sorted(EXPRESSION_FUNCTIONS))) from None
    if not is_number(result):
        raise _Invalid(path, f'{text!r} gives {_describe(result)}, not a number')
    try:
        return float(result)
    except OverflowError:
        raise _Invalid(path, f'{text!r} gives a number beyond the largest double (1.8e308); '
                             'expressions must stay within the field\'s range') from None


# Python counts True as 1 and comparisons give truth values: in an expression, `True + h` or
# `(h > 1) * 2` would be taken as numbers; a scene's values are numbers, never truth values.
_TRUTH_NODES = (ast.Compare, ast.BoolOp, ast.Not)


def _refuse_truth_values(text: str, path: str) -> None:
    for node in ast.walk(ast.parse(text.strip(), mode='eval')):
        constant = isinstance(node, ast.Constant) and (node.value is None or isinstance(
            node.value, bool))
        if constant or isinstance(node, _TRUTH_NODES):
            what = (repr(node.value) if constant else 'a comparison or a logical operation')
            raise _Invalid(path, f'cannot evaluate {text!r}: {what} is not a number; '
                                 'expressions are arithmetic of numbers and parameters')
