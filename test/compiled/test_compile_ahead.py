"""A first compile shared with a helper process: the locks, the plan, the helper's lifetime.

The processes run on a copy of the package with a probe (``test_kernel_cache``) and their own
cache directory; the shipped plans are checked against what the default run compiles here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import time

from paths import REPO
import pytest
from test_kernel_cache import copy_package, NOTICE, probe_env, run

from feeder_sim.compiled import ahead
from feeder_sim.run import run as run_scene
from feeder_sim.simulator import Simulator

PROBE = 'feeder_sim._probe.caller:probe'

OTHER = '''
from feeder_sim.compiled.jit import jit


@jit
def ping(x):
    return x + 1
'''

# holds the probe's lock, compiles it when told, reports what it compiled
HOLDER = f'''
import json, sys
from feeder_sim.compiled import ahead
from feeder_sim._probe.caller import probe
with ahead.kernel_lock({PROBE!r}):
    print('locked', flush=True)
    sys.stdin.readline()
    value = probe(3.0)
print(json.dumps({{'value': value, 'misses': sum(probe.stats.cache_misses.values())}}))
'''

ASKER = '''
import json, time
from feeder_sim._probe.caller import probe
from feeder_sim.compiled.jit import kernel_load_seconds
print('asking', flush=True)
t0 = time.monotonic()
value = probe(3.0)
print(json.dumps({'value': value, 'hits': sum(probe.stats.cache_hits.values()),
                  'misses': sum(probe.stats.cache_misses.values()),
                  'first_call_s': time.monotonic() - t0, 'load_s': kernel_load_seconds()}))
'''

RECORD = '''
import json
from feeder_sim.compiled import ahead
from feeder_sim._probe.caller import probe
with ahead.record() as records:
    probe(3.0)
print(json.dumps(ahead.encode_plan(records)))
'''

# starts the helper of plan 'probe' by a first compile, waits for it, then runs the probe
HELPED = '''
import json, sys
from feeder_sim.compiled import ahead
from feeder_sim.compiled import jit as compiled_jit
from feeder_sim._probe.other import ping
from feeder_sim._probe.caller import probe
compiled_jit.expect('probe')
ping(1)
helper = ahead._helper['process']
print(json.dumps({'pid': helper.pid}), flush=True)
if sys.argv[-1] == 'wait':
    helper.wait(timeout=60)
    value = probe(3.0)
    print(json.dumps({'value': value, 'hits': sum(probe.stats.cache_hits.values()),
                      'misses': sum(probe.stats.cache_misses.values()),
                      'helper_exit': helper.returncode}))
else:
    sys.stdin.readline()
'''


def start(tree: Path, cache: Path, code: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-c', code, *args], cwd=tree,
                            env=probe_env(tree, cache), stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie has ended; only its parent has not read its status yet
    with open(f'/proc/{pid}/stat') as f:
        return f.read().rsplit(')', 1)[1].split()[0] != 'Z'


def test_simulated_wall_time_of_a_hand_worked_schedule():
    # items 0 and 1 take 4 s each, item 2 (2 s) calls both. Alone: 10 s. The helper on
    # {1, 2}: it does 1 in [0, 4] while the run does 0; then 2 in [4, 6]; the run waits: 6 s.
    costs, deps = [4.0, 4.0, 2.0], [[], [], [0, 1]]
    assert ahead.simulate(costs, deps, {1, 2}, helper_start_s=0.0) == 6.0
    # {2} alone: the helper waits for the run's 0 and 1 (8 s), then 2: no gain
    assert ahead.simulate(costs, deps, {2}, helper_start_s=0.0) == 10.0
    # a helper starting 1 s late: 1 in [1, 5], 2 in [5, 7]
    assert ahead.simulate(costs, deps, {1, 2}, helper_start_s=1.0) == 7.0
    items = [{'cost_s': c, 'deps': d} for c, d in zip(costs, deps, strict=True)]
    assert ahead.helper_share(items, helper_start_s=0.0) == ([1, 2], 6.0)


def test_a_kernel_two_processes_ask_for_is_compiled_once(tmp_path):
    tree = copy_package(tmp_path / 'tree')
    cache = tmp_path / 'cache'
    holder = start(tree, cache, HOLDER)
    asker = None
    try:
        assert holder.stdout.readline().strip() == 'locked'
        asker = start(tree, cache, ASKER)
        assert asker.stdout.readline().strip() == 'asking'
        time.sleep(1.0)
        assert asker.poll() is None, 'compiled while the lock was held'
        holder.stdin.write('\n')
        holder.stdin.flush()
        held, _ = holder.communicate(timeout=120)
        asked, err = asker.communicate(timeout=120)
    finally:
        for p in (holder, asker):
            if p is not None and p.poll() is None:
                p.kill()
    assert json.loads(held.splitlines()[-1]) == {'value': 7.0, 'misses': 1}
    # it waited, then loaded what the holder saved
    asked = json.loads(asked.splitlines()[-1])
    assert (asked['value'], asked['hits'], asked['misses']) == (7.0, 1, 0), err
    # the wait counts as first use, not as the work of whoever called (the node's pacing)
    assert asked['first_call_s'] > 1.0
    assert asked['load_s'] == pytest.approx(asked['first_call_s'], rel=0.05)
    assert NOTICE not in err


def write_plan(tree: Path, cache: Path, helper: list[int] | None) -> dict:
    """Record the probe's compile (on its own cache) as plan 'probe' of the copy ``tree``."""
    plan, _ = run(tree, cache, RECORD)
    assert [it['kernel'] for it in plan['items']] == ['feeder_sim._probe.callee:scale', PROBE]
    assert plan['items'][1]['deps'] == [0]
    assert plan['items'][0]['signature'] == ['float64']
    if helper is not None:
        plan['helper'] = helper
    folder = tree / 'feeder_sim' / 'compiled' / 'plans'
    folder.mkdir(exist_ok=True)
    (folder / 'probe.json').write_text(json.dumps(plan))
    (tree / 'feeder_sim' / '_probe' / 'other.py').write_text(OTHER)
    return plan


def test_the_helper_compiles_its_share_for_the_run_to_load(tmp_path):
    tree = copy_package(tmp_path / 'tree')
    write_plan(tree, tmp_path / 'record', helper=[0, 1])
    helped = start(tree, tmp_path / 'cache', HELPED, 'wait')
    out, err = helped.communicate(timeout=120)
    assert helped.returncode == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    assert lines[1] == {'value': 7.0, 'hits': 1, 'misses': 0, 'helper_exit': 0}
    assert not alive(lines[0]['pid'])
    notices = [line for line in err.splitlines() if NOTICE in line]
    assert len(notices) == 1 and ', in two processes, ' in notices[0], err


@pytest.mark.parametrize('how', ['killed', 'exits'])
def test_the_helper_ends_with_its_run(tmp_path, how):
    tree = copy_package(tmp_path / 'tree')
    # the helper's item needs the run's, which never comes: the helper waits
    write_plan(tree, tmp_path / 'record', helper=[1])
    helped = start(tree, tmp_path / 'cache', HELPED, 'hold')
    try:
        pid = json.loads(helped.stdout.readline())['pid']
        time.sleep(1.0)
        assert alive(pid)
        if how == 'killed':
            helped.send_signal(signal.SIGKILL)
        else:
            helped.stdin.write('\n')
            helped.stdin.flush()
        helped.wait(timeout=30)
        deadline = time.monotonic() + 2.0
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(pid)
    finally:
        if helped.poll() is None:
            helped.kill()


def test_no_helper_when_switched_off_or_without_a_plan(monkeypatch):
    monkeypatch.setattr(ahead, '_helper', {'process': None})
    monkeypatch.setenv(ahead.HELPER_ENV_VAR, '0')
    assert not ahead.start_helper('event_driven')
    monkeypatch.setenv(ahead.HELPER_ENV_VAR, '1')
    assert not ahead.start_helper('no_such_method')
    assert ahead._helper['process'] is None


def test_the_default_run_has_a_plan():
    # the first-use target is the default run's; time_stepping's first compile is
    # mostly one kernel's (its whole step, one LLVM module): a helper would take 5 % off
    assert sorted(p.stem for p in ahead.PLAN_DIR.glob('*.json')) == ['event_driven']


@pytest.mark.parametrize('method', sorted(p.stem for p in ahead.PLAN_DIR.glob('*.json')))
def test_each_shipped_plan_is_what_the_default_run_compiles(method):
    plan = ahead.load_plan(method)
    assert plan is not None, f'record it: python test/compile_plan.py {method}'
    planned = {(it['kernel'], ahead._args(it)) for it in plan['items']}
    # the run the plan was recorded from (test/compile_plan.py): the same kernels, in order
    with ahead.record() as records:
        run_scene(Simulator('track_one_box', method=method), 0.1)
    # what this process compiled or loaded (on a warm cache the kernels Python calls; their
    # callees come inside them) is planned ...
    unplanned = {f'{r["kernel"]}{r["args"]}' for r in records} - \
        {f'{k}{a}' for k, a in planned}
    assert not unplanned, f'record again: python test/compile_plan.py {method}; {unplanned}'
    # ... and everything planned is in the cache for these sources: used by this run or one
    # before it (a kernel nobody asks for any more would be in no index)
    stale = [f'{item["kernel"]}{tuple(item["signature"])}' for item in plan['items']
             if not ahead.cached(ahead._dispatcher(item),
                                          ahead._args(item))]
    assert not stale, f'record again: python test/compile_plan.py {method}; stale: {stale}'
    # callees come first (the order compiles ended), so no one waits on a later kernel
    assert all(d < i for i, it in enumerate(plan['items']) for d in it['deps'])
    assert plan['with_helper_s'] < 0.8 * plan['alone_s']


def test_feeder_sim_compile_leaves_nothing_for_the_first_run(tmp_path):
    root = REPO
    env = probe_env(root, tmp_path / 'cache')

    def cli(*args: str) -> subprocess.CompletedProcess:
        done = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', *args], cwd=root,
                              env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        return done

    compiled = cli('compile', '--method', 'impulse_based')
    assert NOTICE in compiled.stderr
    line = compiled.stdout.splitlines()[0]
    assert line.startswith('track_one_box impulse_based: ')
    # nearly all of it compiling: the 0.05 s of simulation costs milliseconds
    loading, total = (float(x) for x in re.findall(r'([\d.]+) s', line))
    assert loading > 1.0 and loading <= total
    first = cli('run', 'track_one_box', '--method', 'impulse_based', '--duration', '0.05')
    assert NOTICE not in first.stderr
