"""The first compile's progress: what it says, how often, and when it stops."""

import io
import time

import pytest

from feeder_sim.compiled import progress as P

PLAN = [('feeder_sim.a:f', 1.0), ('feeder_sim.a:g', 3.0), ('feeder_sim.a:f', 4.0)]


def test_the_estimate_scales_the_plans_times_by_the_pace_so_far():
    progress = P.CompileProgress(PLAN, busy=lambda: True, stream=io.StringIO(), tty=False)
    assert progress.fraction() == 0.0 and progress.left_s(10.0) is None
    progress.compiled('feeder_sim.a:g')           # 3 of 8 recorded seconds
    progress.compiled('feeder_sim.b:not_planned')
    assert progress.done == 2
    assert progress.fraction() == pytest.approx(3 / 8)
    # 3 recorded seconds took 6 s here: the 5 left take 10 s
    assert progress.left_s(6.0) == pytest.approx(10.0)
    assert '2 done (38 % of the plan)' in progress.text()


def test_without_a_plan_it_counts_kernels_and_time():
    progress = P.CompileProgress(None, busy=lambda: True, stream=io.StringIO(), tty=False)
    progress.compiled('feeder_sim.a:f')
    assert progress.fraction() is None and progress.left_s(5.0) is None
    assert progress.text().startswith('compiling kernels: 1 done, ')


@pytest.mark.parametrize('tty', [False, True])
def test_lines_while_busy_then_one_closing_line(monkeypatch, tty):
    monkeypatch.setattr(P, 'LINE_INTERVAL_S', 0.5)
    monkeypatch.setattr(P, 'IDLE_S', 0.6)
    monkeypatch.setattr(P, '_TICK_S', 0.05)
    busy = {'now': True}
    stream = io.StringIO()
    progress = P.CompileProgress(PLAN, busy=lambda: busy['now'], stream=stream, tty=tty)
    progress.start()
    progress.compiled('feeder_sim.a:f')
    time.sleep(1.3)
    busy['now'] = False
    progress._thread.join(timeout=5)
    assert not progress.running()
    out = stream.getvalue()
    if not tty:
        lines = out.splitlines()
        assert 2 <= sum(line.startswith('compiling kernels: 1 done') for line in lines) <= 3
    assert out.rstrip().splitlines()[-1].startswith('compiled 1 kernel in ')
