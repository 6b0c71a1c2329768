"""The README's commands run as written from the quick start's venv, and leave the checkout clean.

Every command in the README's ``bash`` blocks is either run here, in a copy of the checkout
(its tracked files, committed afresh so that ``git status`` shows what the commands changed),
or listed below with the reason it is not: a placeholder to fill in, a run of minutes that
another test makes with the same code, or a command that needs what a test machine has not
(a display, the ros2 CLI, a colcon workspace). A command added to the README without either
fails the test, so the guide cannot drift from the tool. ``.venv/bin/`` stands for the venv
this test runs in."""

from __future__ import annotations

import json
from pathlib import Path
import re
import shlex
import shutil
import subprocess
import sys

from mcap_ros2.reader import read_ros2_messages
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
VENV_BIN = Path(sys.executable).parent

# Run, in this order (later ones read what earlier ones wrote); each takes seconds once the
# kernels are compiled.
RUN = (
    '.venv/bin/feeder-sim run track_one_box --duration 5 --record out/run.mcap '
    '--summary out/run.json',
    '.venv/bin/feeder-sim scenes',
    '.venv/bin/feeder-sim replay out/run.mcap',
    '.venv/bin/feeder-sim accuracy --list',
    '.venv/bin/feeder-sim stability --list',
)

# Not run here, by the start of the command, with the reason.
NOT_RUN = {
    'make run': 'the quick start itself: sets up a venv (CI runs make test, its twin)',
    'make test': 'the quick start itself: this suite',
    '.venv/bin/feeder-sim run my_scene.yaml': 'placeholder scene (test_cli runs --method, '
                                              '--publish-rate)',
    '.venv/bin/feeder-sim compile my_scene.yaml': 'placeholder scene (test_compile_ahead)',
    '.venv/bin/feeder-sim paper': '20 s; test_paper_scenes makes the same figures',
    '.venv/bin/feeder-sim accuracy --out': '30 s; test_accuracy runs the same report',
    '.venv/bin/feeder-sim stability --out': 'minutes; test_stability runs its scenes',
    '.venv/bin/feeder-sim study': 'a Dask cluster for 20 s or a placeholder; test_studies',
    '.venv/bin/python benchmarks/': 'a benchmark: minutes, timings are not tests',
    '.venv/bin/feeder-sim replay out/track_one_box.mcap': "make run's log; the replay of "
                                                          'out/run.mcap above is the same',
    '.venv/bin/rerun': 'opens a viewer (needs a display); test_replay loads the .rrd back',
    '.venv/bin/sim_node': 'the example cell; test_sim_node runs it with its controller',
    '.venv/bin/python examples/queue_controller.py': 'needs the node above; test_sim_node',
    'feeder-sim node': 'needs a running node named in the command; test_node_client',
    'ros2 ': 'the ros2 CLI is not in the venv; the feeder-sim node lines are its twins',
    'python3 -m venv': 'the colcon recipe: a second venv and workspace '
                       '(test_sim_node_process builds the package with colcon)',
    'pip install': 'the colcon recipe',
    'mkdir -p ~/ws': 'the colcon recipe',
    'git -C /path/to': 'the colcon recipe',
    'python src/feeder_sim': 'the colcon recipe',
    'colcon build': 'the colcon recipe',
}


def readme_commands(text: str) -> list[str]:
    """The commands of the README's ``bash`` blocks: continuation lines joined, comments and
    blank lines dropped."""
    commands = []
    for block in re.findall(r'^```bash\n(.*?)^```', text, flags=re.S | re.M):
        joined = re.sub(r'\\\n\s*', ' ', block)
        for line in joined.splitlines():
            line = line.strip()
            if line and not line.startswith('#'):
                commands.append(' '.join(shlex.split(line, comments=True)))
    return commands


def readme_python(text: str) -> list[str]:
    """The README's ``python`` blocks."""
    return re.findall(r'^```python\n(.*?)^```', text, flags=re.S | re.M)


def test_every_readme_command_is_run_here_or_has_a_reason():
    commands = readme_commands(README.read_text())
    assert len(commands) > 20
    unlisted = [c for c in commands
                if c not in RUN and not any(c.startswith(p) for p in NOT_RUN)]
    assert not unlisted, f'README commands neither run nor listed in {__file__}: {unlisted}'
    # each run command is still in the README, as written
    assert set(RUN) <= set(commands)
    # and each reason still covers a command
    assert all(any(c.startswith(p) for c in commands) for p in NOT_RUN), \
        [p for p in NOT_RUN if not any(c.startswith(p) for c in commands)]


@pytest.fixture(scope='module')
def checkout(tmp_path_factory) -> Path:
    """A copy of the checkout's tracked files, committed, with ``.venv/bin`` this venv's."""
    where = tmp_path_factory.mktemp('checkout')
    files = subprocess.run(['git', 'ls-files', '-z'], cwd=ROOT, capture_output=True,
                           check=True).stdout.decode().split('\0')
    for name in filter(None, files):
        if (ROOT / name).is_file():
            (where / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, where / name)
    git = ['git', '-c', 'user.name=readme', '-c', 'user.email=readme@localhost']
    for args in (['init', '-q'], ['add', '-A'], ['commit', '-qm', 'checkout']):
        subprocess.run(git + args, cwd=where, check=True)
    (where / '.venv').mkdir()
    (where / '.venv' / 'bin').symlink_to(VENV_BIN, target_is_directory=True)
    return where


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(shlex.split(command), cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.timeout(600)
def test_the_quick_commands_run_as_written_and_leave_the_checkout_clean(checkout):
    printed = {}
    for command in RUN:
        done = _run(command, checkout)
        assert done.returncode == 0, (command, done.stderr[-2000:])
        printed[command] = done.stdout
    # what they wrote is what the README says: a 5 s log, its summary, the rerun recording
    summary = json.loads((checkout / 'out' / 'run.json').read_text())
    assert summary['scene'] == 'track_one_box' and summary['simulated_s'] == pytest.approx(5.0)
    stamps = [m.log_time_ns for m in read_ros2_messages(str(checkout / 'out' / 'run.mcap'),
                                                        topics=['/feeder_sim/part_poses'])]
    assert stamps[-1] - stamps[0] == pytest.approx(5e9, abs=0.1e9)
    assert (checkout / 'out' / 'run.rrd').stat().st_size > 10_000
    scenes = printed['.venv/bin/feeder-sim scenes']
    assert all(p.stem in scenes for p in (ROOT / 'config').glob('*.yaml')
               if not p.name.endswith('params.yaml'))
    for block in readme_python(README.read_text()):
        done = subprocess.run([sys.executable, '-c', block], cwd=checkout, capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 0, (block, done.stderr[-2000:])
    status = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=all'],
                            cwd=checkout, capture_output=True, text=True, check=True).stdout
    assert status == '', f'README commands changed the checkout:\n{status}'
