"""What every stepping method offers the simulator, and what it hands back.

A method advances a :class:`~feeder_sim.model.world.State` in place to a given time and returns
the contacts it used on the way with the impulses they transmitted; ``reset`` tells it that the
prescribed motion changed (a vibration command), so anything it derived from that motion is
stale. The simulator sees nothing else of a method.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import math
import numbers
from typing import ClassVar, Protocol

import numpy as np

from feeder_sim.contact.dynamics import ContactSet, SolverStats
from feeder_sim.model.scene import Scene, SolverSpec, STEP_RULES, StepRule
from feeder_sim.model.world import State, World


@dataclass
class StepContacts:
    """Contacts of one step (or event) and the impulses (N s) they transmitted."""

    cs: ContactSet
    normal_impulse: np.ndarray
    tangent_impulse: np.ndarray


class Stepper(Protocol):
    """A stepping method, built as ``Method(world, spec, stats, settings)``.

    Its class carries the method's policy, which the simulator, the node and the reports ask
    for instead of branching on its name."""

    name: ClassVar[str]
    step_rule: ClassVar[StepRule]
    """Its step from the scene's drives (the scene's ``STEP_RULES``)."""
    fixed_steps: ClassVar[bool]
    """It advances in steps of at most ``spec.time_step``, whose count a frame's cost
    follows; False: from event to event (``after_event`` sees each)."""
    error_setting: ClassVar[str]
    """What a numerical-error estimate varies: ``'time_step'`` (s) or ``'tolerance'``."""
    order: ClassVar[int | None]
    """Its order of convergence in ``error_setting``, None where it is not known."""

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: object | None = None) -> None: ...

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Move ``state`` to simulated time ``t_end`` (s); the contacts of every step taken."""
        ...

    def reset(self) -> None:
        """The prescribed motion changed at ``state.t``: forget what was derived from it."""
        ...

    @classmethod
    def step_for(cls, scene: Scene) -> float | None:
        """The step (s) it takes on ``scene`` when the scene's step was chosen for another
        method; None where the scene's step stands."""
        ...


def _parse_range(rule: str) -> tuple[float, float, bool, bool]:
    """'>= 0', '> 0', '[0, 1]', '(0, 2)' and the like: (low, high, low included, high
    included)."""
    if rule[0] in '[(':
        lo, hi = (float(x) for x in rule[1:-1].split(','))
        return lo, hi, rule[0] == '[', rule[-1] == ']'
    op, value = rule.split()
    return float(value), math.inf, op == '>=', False


class CheckedSettings:
    """A stepping method's settings dataclass whose every assignment, at construction or
    later, is checked against the field's annotated type (``bool``, ``int``, ``float``, each
    optionally ``| None``) and the range in ``LIMITS`` (``'>= 0'``, ``'> 0'``, ``'[0, 1]'``,
    ``'(0, 2)'``); floats must be finite. A bad value raises a ValueError naming the field, the
    allowed values and the value given, so that a setting can never hang or break a run
    later (``pgs_check = 0`` would sweep forever)."""

    LIMITS: ClassVar[dict[str, str]] = {}
    # assignments so far: what was derived from the settings is current while it is unchanged
    version: int = 0

    def __setattr__(self, name: str, value: object) -> None:
        f = type(self).__dataclass_fields__.get(name)  # type: ignore[attr-defined]
        if f is not None:
            value = self._checked(name, str(f.type), value)
            object.__setattr__(self, 'version', self.version + 1)
        object.__setattr__(self, name, value)

    def _checked(self, name: str, annotation: str, value: object) -> object:
        kinds = [k.strip() for k in annotation.split('|')]
        rule = self.LIMITS.get(name)
        what = {'bool': 'true or false', 'int': 'an integer (64 bits)',
                'float': 'a finite number'}[kinds[0]]
        want = what + (f' {rule}' if rule and rule[0] in '<>' else f' in {rule}' if rule else '')
        if 'None' in kinds:
            want += ' or None'
        if value is None and 'None' in kinds:
            return None
        ok = False
        if kinds[0] == 'bool':
            ok = isinstance(value, (bool, np.bool_))
            value = bool(value) if ok else value
        elif not isinstance(value, (bool, np.bool_)):
            if kinds[0] == 'int' and isinstance(value, numbers.Integral):
                # compiled kernels take int64
                ok = -2 ** 63 <= int(value) < 2 ** 63
                value = int(value) if ok else value
            elif kinds[0] == 'float' and isinstance(value, numbers.Real):
                try:
                    ok = math.isfinite(float(value))
                except OverflowError:       # an integer beyond any float
                    ok = False
                value = float(value) if ok else value
        if ok and rule and not isinstance(value, bool):
            lo, hi, lo_in, hi_in = _parse_range(rule)
            ok = ((value >= lo if lo_in else value > lo)
                  and (value <= hi if hi_in else value < hi))
        if not ok:
            raise ValueError(f'{type(self).__name__}.{name} must be {want}, got {value!r}')
        return value


class StepperBase:
    """What every method keeps: the world, the scene's solver spec, the counters it adds to,
    and its own settings (``settings_type()`` when none are given). A method derives what it
    needs from them in ``prepare``."""

    settings_type: type
    # the policy (see Stepper); step_rule is the scene's STEP_RULES[name]
    name: ClassVar[str]
    step_rule: ClassVar[StepRule]
    fixed_steps: ClassVar[bool]
    error_setting: ClassVar[str]
    order: ClassVar[int | None]
    # Called with the state and the contacts reported since the previous call at every event a
    # method locates (event_driven); the energy check of :mod:`feeder_sim.simulator` uses it.
    after_event: Callable[[State, list[StepContacts]], None] | None = None

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.step_rule = STEP_RULES[cls.name]

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: object | None = None) -> None:
        self.world = world
        self.spec = spec
        self.stats = stats
        if settings is not None and not isinstance(settings, self.settings_type):
            raise TypeError(f'{spec.method} takes {self.settings_type.__name__} settings, '
                            f'got {type(settings).__name__}')
        self.settings = settings or self.settings_type()
        self.prepare()

    def prepare(self) -> None:
        """Build what the method derives from its world, spec and settings."""

    @classmethod
    def step_for(cls, scene: Scene) -> float | None:
        """A method whose error its step sets (a known order in the step) takes its own
        rule's step on a scene whose step was chosen for another method, where that is finer;
        for the others the scene's step (a largest step) stands."""
        if cls.order is None or cls.error_setting != 'time_step':
            return None
        step = cls.step_rule.step(scene.drive_frequencies_hz())
        return step if step < scene.solver.time_step else None
