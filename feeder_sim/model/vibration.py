"""Prescribed sinusoidal motion of kinematic bodies (the vibrating track).

A drive moves its body along a fixed world direction by ``d(t) = A sin(phi(t)) + c(t)``.
Commands change amplitude and frequency during a run. The displacement never jumps: the new
sinusoid starts at the phase where it passes through the current displacement, moving the same
way as before; when that is impossible (the new amplitude is smaller than the current
displacement, or zero) the phase is kept and the mismatch ``c`` fades out over one period with
a raised-cosine blend, whose velocity is zero at both ends. Velocity may jump at a command, as it
would when a real drive is switched: contacts see that as an impact.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.jit import inner
from feeder_sim.model.checks import is_number

TWO_PI = 2.0 * math.pi

# The smallest non-zero drive values the physics resolves. An amplitude below the contact
# tolerances (1 nm) moves nothing a contact can see, and its product with omega underflows
# for the denormal values a wrong unit or a corrupted message produces; a frequency below
# 1 mHz (a period over 1000 s) is a slow displacement, not a vibration.
MIN_AMPLITUDE_M = 1e-9
MIN_FREQUENCY_HZ = 1e-3
# The largest, wherever a drive value comes from (a scene file, a command from Python or ROS):
# feeders vibrate at 1e-5 to 1e-3 m and 10 to 300 Hz. Far beyond, a value is a mistake whose
# physics has no bound on its work (event_driven would locate every impact of a part on a
# track vibrating at 1e9 Hz).
MAX_AMPLITUDE_M = 0.1
MAX_FREQUENCY_HZ = 1000.0


def drive_value_problem(name: str, value: float) -> str | None:
    """Why a drive ``amplitude`` (m) or ``frequency`` (Hz) cannot be used, or None.

    Zero is allowed (the drive is off); so is anything from the minimum to the maximum."""
    minimum, maximum, unit = {'amplitude': (MIN_AMPLITUDE_M, MAX_AMPLITUDE_M, 'm'),
                              'frequency': (MIN_FREQUENCY_HZ, MAX_FREQUENCY_HZ, 'Hz')}[name]
    if 0.0 < value < minimum:
        return (f'{name} {value:g} {unit} is below the smallest the physics resolves '
                f'({minimum:g} {unit}); give 0 to stop the drive, or at least {minimum:g} {unit}')
    if value > maximum:
        return (f'{name} {value:g} {unit} is above the largest a drive takes '
                f'({maximum:g} {unit}); give at most {maximum:g} {unit}')
    return None


def check_command(amplitude_m: float, frequency_hz: float) -> None:
    """Refuse (ValueError, one line) a drive command no drive takes."""
    if not all(is_number(x) and math.isfinite(x) and x >= 0
               for x in (amplitude_m, frequency_hz)):
        raise ValueError('amplitude_m and frequency_hz must be finite numbers >= 0, got '
                         f'{amplitude_m!r}, {frequency_hz!r}')
    for name, value in (('amplitude', amplitude_m), ('frequency', frequency_hz)):
        if (problem := drive_value_problem(name, value)) is not None:
            raise ValueError(problem)


@dataclass(frozen=True)
class _Segment:
    start_s: float
    amplitude_m: float
    frequency_hz: float
    phase_rad: float          # phase at start_s
    offset_m: float = 0.0     # c(start_s); fades to zero over blend_s
    blend_s: float = 0.0


@dataclass
class Drive:
    """Displacement of one kinematic body along ``direction`` (unit vector, world frame)."""

    direction: np.ndarray
    amplitude_m: float
    frequency_hz: float
    phase_rad: float = 0.0
    _segments: list[_Segment] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self.direction = np.asarray(self.direction, dtype=float)
        self._initial = (self.amplitude_m, self.frequency_hz, self.phase_rad)
        self.reset()

    def segment(self, t: float) -> _Segment:
        # Commands arrive in time order, so the active segment is nearly always the last one.
        for seg in reversed(self._segments):
            if t >= seg.start_s:
                return seg
        return self._segments[0]

    def motion(self, t: float) -> tuple[float, float, float]:
        """Displacement (m), velocity (m/s) and acceleration (m/s^2) along ``direction``.

        The reference of :func:`segment_motion`, which compiled steppers call."""
        seg = self.segment(t)
        tau = t - seg.start_s
        omega = TWO_PI * seg.frequency_hz
        phi = seg.phase_rad + omega * tau
        s, c = math.sin(phi), math.cos(phi)
        d = seg.amplitude_m * s
        v = seg.amplitude_m * omega * c
        a = -seg.amplitude_m * omega * omega * s
        if seg.offset_m and tau < seg.blend_s:
            k = math.pi / seg.blend_s
            d += 0.5 * seg.offset_m * (1.0 + math.cos(k * tau))
            v -= 0.5 * seg.offset_m * k * math.sin(k * tau)
            a -= 0.5 * seg.offset_m * k * k * math.cos(k * tau)
        return d, v, a

    def next_change_after(self, t: float) -> float:
        """The next time after ``t`` at which the motion stops being smooth (end of a blend)."""
        seg = self.segment(t)
        end = seg.start_s + seg.blend_s
        return end if seg.offset_m and end > t else math.inf

    def command(self, t: float, amplitude_m: float, frequency_hz: float) -> None:
        """Switch to a new amplitude and frequency from time ``t`` on, keeping d(t) continuous.

        The values are the caller's to check (:func:`check_command`, as the simulator does at
        its boundary): a drive takes what it is given."""
        d, v, _ = self.motion(t)
        old = self.segment(t)
        old_phase = old.phase_rad + TWO_PI * old.frequency_hz * (t - old.start_s)
        offset = 0.0
        if amplitude_m > 0 and abs(d) <= amplitude_m:
            phase = math.asin(d / amplitude_m)
            if v < 0:
                phase = math.pi - phase
        else:
            phase = old_phase
            offset = d - amplitude_m * math.sin(phase)
        period = 1.0 / frequency_hz if frequency_hz > 0 else (
            1.0 / old.frequency_hz if old.frequency_hz > 0 else 0.0)
        if period == 0.0:
            offset = 0.0  # nothing was moving: d == 0 already
        self._segments = [s for s in self._segments if s.start_s < t]
        self._segments.append(_Segment(t, amplitude_m, frequency_hz, phase, offset, period))
        self.amplitude_m, self.frequency_hz = amplitude_m, frequency_hz

    def reset(self) -> None:
        """Back to the motion given at construction, as at t = 0."""
        amplitude_m, frequency_hz, phase_rad = self._initial
        self._segments = [_Segment(0.0, amplitude_m, frequency_hz, phase_rad)]
        self.amplitude_m, self.frequency_hz = amplitude_m, frequency_hz


class DriveSegments(NamedTuple):
    """The drive table: the sinusoid each drive follows from a time on, one row per drive.

    What compiled steppers take instead of :class:`Drive` objects (:func:`drive_segments`
    builds it, :func:`segment_motion` evaluates a row as :meth:`Drive.motion` does)."""

    direction: np.ndarray      # (nd, 2) unit vector of the displacement, world frame
    base_m: np.ndarray         # (nd, 2) position of the driven body at zero displacement
    start_s: np.ndarray        # (nd,) start of the segment
    amplitude_m: np.ndarray    # (nd,)
    omega_rad_s: np.ndarray    # (nd,) 2 pi f
    phase_rad: np.ndarray      # (nd,) phase at start_s
    offset_m: np.ndarray       # (nd,) mismatch c(start_s) of a command, fading over blend_s
    blend_s: np.ndarray        # (nd,)

    def blending(self, t: float) -> bool:
        """Whether a drive is still blending out a command's mismatch at ``t`` (s)."""
        return bool(np.any((self.offset_m != 0.0) & (self.start_s + self.blend_s > t)))

    def stroke_m(self) -> np.ndarray:
        """(nd,) length of the segment a driven body never leaves (m)."""
        return 2.0 * self.amplitude_m + np.abs(self.offset_m)

    def speed_bound_mps(self) -> float:
        """A bound on every drive's speed over its segment (m/s)."""
        blend = np.divide(np.pi * np.abs(self.offset_m), self.blend_s,
                          out=np.zeros_like(self.blend_s), where=self.blend_s > 0)
        return float(np.max(self.amplitude_m * self.omega_rad_s + blend, initial=0.0))


def drive_segments(drives: Sequence[Drive], base_m: np.ndarray, t: float) -> DriveSegments:
    """The drive table of ``drives`` (bodies at ``base_m``, (nd, 2)) from time ``t`` on (s)."""
    return drive_table(drives, [drive.segment(t) for drive in drives], base_m)


def drive_table(drives: Sequence[Drive], segs: Sequence[_Segment],
                base_m: np.ndarray) -> DriveSegments:
    """The drive table of ``drives`` (bodies at ``base_m``, (nd, 2)) on segments ``segs``."""
    nd = len(segs)
    return DriveSegments(
        np.array([drive.direction for drive in drives], dtype=float).reshape(nd, 2),
        np.array(base_m, dtype=float).reshape(nd, 2),
        np.array([s.start_s for s in segs], dtype=float),
        np.array([s.amplitude_m for s in segs], dtype=float),
        np.array([TWO_PI * s.frequency_hz for s in segs], dtype=float),
        np.array([s.phase_rad for s in segs], dtype=float),
        np.array([s.offset_m for s in segs], dtype=float),
        np.array([s.blend_s for s in segs], dtype=float))


@inner
def segment_motion(t, drives, d):
    """Displacement (m), velocity (m/s) and acceleration (m/s^2) of row ``d`` of the drive
    table at time ``t`` (s), as :meth:`Drive.motion`."""
    tau = t - drives.start_s[d]
    omega = drives.omega_rad_s[d]
    amplitude = drives.amplitude_m[d]
    phi = drives.phase_rad[d] + omega * tau
    s = math.sin(phi)
    disp = amplitude * s
    v = amplitude * omega * math.cos(phi)
    a = -amplitude * omega * omega * s
    offset, blend = drives.offset_m[d], drives.blend_s[d]
    if offset != 0.0 and tau < blend:
        k = math.pi / blend
        disp += 0.5 * offset * (1.0 + math.cos(k * tau))
        v -= 0.5 * offset * k * math.sin(k * tau)
        a -= 0.5 * offset * k * k * math.cos(k * tau)
    return disp, v, a


@dataclass(frozen=True)
class CommandLimits:
    """Bounds a vibration command must respect; anything outside is a mistake, not a request."""

    max_amplitude_m: float = MAX_AMPLITUDE_M
    max_frequency_hz: float = MAX_FREQUENCY_HZ


def parse_command(data, limits: CommandLimits = CommandLimits()) -> tuple[float, float]:
    """``(amplitude_m, frequency_hz)`` from a ``[amplitude_m, frequency_hz]`` command.

    Raises ``ValueError`` saying what is wrong and what is expected, so that a node can reject
    the command with that text and keep the previous one.
    """
    values = list(data)
    if len(values) != 2:
        raise ValueError(f'expected data = [amplitude_m, frequency_hz], got {len(values)} '
                         'values')
    for name, value in zip(('amplitude', 'frequency'), values, strict=True):
        if not is_number(value):
            raise ValueError(f'{name} is {value!r}; it must be a number')
    amplitude_m, frequency_hz = (float(v) for v in values)
    for name, value, bound, unit in (
            ('amplitude', amplitude_m, limits.max_amplitude_m, 'm'),
            ('frequency', frequency_hz, limits.max_frequency_hz, 'Hz')):
        if not math.isfinite(value):
            raise ValueError(f'{name} is {value!r}; it must be a finite number')
        if value < 0.0:
            raise ValueError(f'{name} {value:g} {unit} is negative; it must be >= 0')
        if value > bound:
            raise ValueError(f'{name} {value:g} {unit} exceeds the limit {bound:g} {unit}')
        if (problem := drive_value_problem(name, value)) is not None:
            raise ValueError(problem)
    return amplitude_m, frequency_hz
