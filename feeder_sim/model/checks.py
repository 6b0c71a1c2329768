"""Checks of the values users give the model: scene files, commands, the Python API."""

from __future__ import annotations

from numbers import Real

import numpy as np


def is_number(x: object) -> bool:
    """A real number that is not a bool (Python, YAML and numpy all count bools as ints)."""
    return isinstance(x, Real) and not isinstance(x, (bool, np.bool_))
