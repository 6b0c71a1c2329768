"""The prescribed track motion: exact sinusoid, continuous displacement across commands."""

import math

import numba
import numpy as np
import pytest

from feeder_sim.model.vibration import (
    check_command,
    CommandLimits,
    Drive,
    drive_segments,
    MAX_AMPLITUDE_M,
    MAX_FREQUENCY_HZ,
    MIN_AMPLITUDE_M,
    MIN_FREQUENCY_HZ,
    parse_command,
    segment_motion,
)


def test_motion_is_the_given_sinusoid():
    d = Drive(np.array([1.0, 0.0]), amplitude_m=1e-3, frequency_hz=50.0, phase_rad=0.3)
    for t in np.linspace(0, 0.1, 17):
        w = 2 * math.pi * 50
        x, v, a = d.motion(t)
        assert x == pytest.approx(1e-3 * math.sin(w * t + 0.3), abs=1e-18)
        assert v == pytest.approx(1e-3 * w * math.cos(w * t + 0.3), rel=1e-12, abs=1e-15)
        assert a == pytest.approx(-1e-3 * w * w * math.sin(w * t + 0.3), rel=1e-12, abs=1e-12)


@pytest.mark.parametrize('t_cmd', [0.0, 0.0031, 0.0113, 0.017])
@pytest.mark.parametrize('amp, freq', [(2e-3, 50.0), (0.5e-3, 30.0), (0.0, 50.0), (1e-3, 0.0),
                                       (0.2e-3, 120.0)])
def test_command_keeps_displacement_continuous(t_cmd, amp, freq):
    d = Drive(np.array([0.0, 1.0]), amplitude_m=1e-3, frequency_hz=50.0)
    before = d.motion(t_cmd)
    d.command(t_cmd, amp, freq)
    after = d.motion(t_cmd)
    assert after[0] == pytest.approx(before[0], abs=1e-15)
    # continuity just after the switch, then the new motion
    eps = 1e-9
    assert abs(d.motion(t_cmd + eps)[0] - after[0]) <= abs(after[1]) * eps + 1e-12
    if amp > 0 and freq > 0 and abs(before[0]) <= amp:
        # the new sinusoid continues the old direction of travel
        assert math.copysign(1, after[1]) == math.copysign(1, before[1]) or before[1] == 0
    # after one period of the new (or old) frequency the motion is the pure new sinusoid
    period = 1 / freq if freq > 0 else 1 / 50.0
    t = t_cmd + 1.5 * period
    x, _, _ = d.motion(t)
    assert abs(x) <= amp + 1e-15


def test_amplitude_zero_brings_the_track_to_rest():
    d = Drive(np.array([1.0, 0.0]), amplitude_m=1e-3, frequency_hz=50.0)
    d.command(0.004, 0.0, 50.0)
    x, v, a = d.motion(0.004 + 0.02 + 1e-6)
    assert (x, v, a) == (0.0, 0.0, 0.0)


def test_invalid_command_is_rejected():
    for bad in [(math.nan, 50.0), (1e-3, math.inf), (-1e-3, 50.0), (1e-3, -1.0)]:
        with pytest.raises(ValueError, match='amplitude_m and frequency_hz'):
            check_command(*bad)
    for bad in [(1e-310, 1e-310), (5e-324, 50.0), (1e-3, 1e-320), (1e-12, 50.0)]:
        with pytest.raises(ValueError, match='below the smallest the physics resolves'):
            check_command(*bad)


@pytest.mark.parametrize('data, field', [
    ([1e-310, 1e-310], 'amplitude'), ([5e-324, 50.0], 'amplitude'), ([1e-3, 1e-320], 'frequency'),
    ([1e-12, 50.0], 'amplitude'), ([1e-3, 1e-6], 'frequency')])
def test_a_command_too_small_to_resolve_is_refused_with_its_field(data, field):
    with pytest.raises(ValueError, match=f'^{field} .* below the smallest .* give 0 to stop'):
        parse_command(data)
    # zero stops the drive, the smallest resolvable values run
    assert parse_command([0.0, 0.0]) == (0.0, 0.0)
    assert parse_command([MIN_AMPLITUDE_M, MIN_FREQUENCY_HZ]) == (1e-9, 1e-3)


@pytest.mark.parametrize('data, field', [
    ([10.0, 50.0], 'amplitude'), ([1e-3, 1e9], 'frequency'), ([0.1000001, 50.0], 'amplitude'),
    ([1e-3, 1000.001], 'frequency'), ([1e300, 1e300], 'amplitude')])
def test_a_drive_value_above_the_largest_is_refused_with_its_field(data, field):
    # The bounds of a scene file hold for commands too, whatever limits a node was given: a
    # track at 1e9 Hz would have event_driven locate a billion impacts per second.
    with pytest.raises(ValueError, match=f'^{field} .* above the largest a drive takes'):
        check_command(*data)
    with pytest.raises(ValueError, match=f'^{field} .* above the largest a drive takes'):
        parse_command(data, CommandLimits(max_amplitude_m=1e301, max_frequency_hz=1e301))
    assert parse_command([MAX_AMPLITUDE_M, MAX_FREQUENCY_HZ]) == (0.1, 1000.0)


@pytest.mark.parametrize('data, field', [(['a', 50.0], 'amplitude'), ([1e-3, None], 'frequency'),
                                         ([True, 50.0], 'amplitude')])
def test_a_command_value_that_is_no_number_is_refused_with_its_field(data, field):
    with pytest.raises(ValueError, match=f'^{field} is .*; it must be a number$'):
        parse_command(data)
    with pytest.raises(ValueError, match='^amplitude_m and frequency_hz must be finite numbers'):
        check_command(*data)


@pytest.mark.parametrize('method', ['event_driven', 'time_stepping', 'impulse_based'])
def test_an_absurd_command_from_python_is_refused_and_the_run_goes_on(method):
    from feeder_sim.simulator import Simulator
    sims = [Simulator('track_one_box', method=method) for _ in range(2)]
    for sim in sims:
        sim.advance(0.02)
    with pytest.raises(ValueError, match='^frequency 1e[+]09 Hz is above the largest'):
        sims[0].command_vibration(1e-3, 1e9)
    for sim in sims:
        sim.advance(0.05)
    assert np.array_equal(sims[0].state.position, sims[1].state.position)


@pytest.mark.parametrize('method', ['event_driven', 'time_stepping', 'impulse_based'])
def test_the_smallest_drive_runs_finite(method):
    from feeder_sim.simulator import Simulator
    sim = Simulator('track_one_box', method=method)
    sim.advance(0.02)
    sim.command_vibration(MIN_AMPLITUDE_M, MIN_FREQUENCY_HZ)
    sim.advance(0.1)
    assert np.all(np.isfinite(sim.state.position)) and np.all(np.isfinite(sim.state.velocity))


def test_reset_restores_the_initial_motion():
    d = Drive(np.array([1.0, 0.0]), amplitude_m=1e-3, frequency_hz=50.0)
    d.command(0.0, 2e-3, 10.0)
    d.reset()
    assert d.motion(0.005)[0] == pytest.approx(1e-3 * math.sin(2 * math.pi * 50 * 0.005))


@pytest.mark.parametrize('method', ['event_driven', 'time_stepping', 'impulse_based'])
def test_a_repeated_setpoint_changes_nothing(method):
    # A ROS controller republishes its setpoint at a fixed rate: commands equal to the running
    # vibration must leave the motion and the stepper alone, to the bit.
    from feeder_sim.simulator import Simulator
    runs = []
    for repeat in (False, True):
        sim = Simulator('track_one_box', method=method)
        drive = sim.world.drives[sim.world.driven[0]]
        for k in range(1, 11):
            if repeat:
                sim.command_vibration(drive.amplitude_m, drive.frequency_hz)
            sim.advance(0.005 * k)
        runs.append(sim)
    plain, repeated = runs
    assert np.array_equal(repeated.state.position, plain.state.position)
    assert np.array_equal(repeated.state.velocity, plain.state.velocity)
    assert repeated.stats.events == plain.stats.events


@numba.njit
def _table_motion(t, drives, row):
    return segment_motion(t, drives, row)


def test_drive_table_rows_move_as_their_drives_across_commands_and_blends():
    # The compiled steppers' drive table is the same model as Drive.motion: to round-off
    # (1e-12 of the amplitude, of A w and of A w^2) before, during and after a command blend.
    drives = [Drive(np.array([1.0, 0.0]), 1e-3, 50.0, 0.3),
              Drive(np.array([0.6, 0.8]), 0.5e-3, 120.0)]
    base = np.array([[0.1, 0.2], [-0.3, 0.0]])
    drives[0].command(0.0123, 2e-4, 60.0)       # smaller than the displacement: a blend
    drives[1].command(0.004, 1e-3, 30.0)        # re-phased, no blend
    for t in np.linspace(0.0124, 0.05, 41):
        table = drive_segments(drives, base, t)
        assert table.base_m.tolist() == base.tolist()
        for row, drive in enumerate(drives):
            ref = drive.motion(t)
            got = _table_motion(t, table, row)
            w = 2 * math.pi * drive.frequency_hz
            scale = max(drive.amplitude_m, 1e-3)
            for x, y, s in zip(got, ref, (scale, scale * w, scale * w * w), strict=True):
                assert x == pytest.approx(y, abs=1e-12 * s)
    assert drive_segments(drives, base, 0.013).blending(0.013)
    assert not drive_segments(drives, base, 0.04).blending(0.04)
