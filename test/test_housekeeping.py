"""What running, benchmarking and testing leave behind: nothing tracked is overwritten by
default, and running needs none of the test tools."""

import os
from pathlib import Path
import re
import runpy
import subprocess

import setuptools

REPO = Path(__file__).resolve().parents[1]
TEST_TOOLS = ('pytest', 'hypothesis', 'ruff', 'colcon', 'pymunk')


def _extras() -> dict[str, list[str]]:
    """setup.py's extras_require, as setup() receives it."""
    seen: dict = {}
    real, cwd = setuptools.setup, os.getcwd()
    setuptools.setup = lambda **kw: seen.update(kw)
    try:
        os.chdir(REPO)                    # its globs are relative to the checkout
        runpy.run_path(str(REPO / 'setup.py'))
    finally:
        setuptools.setup = real
        os.chdir(cwd)
    return seen['extras_require']


def test_make_run_installs_no_test_tools():
    makefile = (REPO / 'Makefile').read_text()
    run_deps = re.search(r'^run: (.+)$', makefile, re.M).group(1).split()
    assert run_deps == ['$(RUN_STAMP)']
    rule = re.search(r'^\$\(RUN_STAMP\):.*\n((?:\t.*\n)+)', makefile, re.M).group(1)
    extras = re.search(r"-e '\.\[([a-z,]+)\]'", rule).group(1).split(',')
    available = _extras()
    installed = [req for extra in extras for req in available[extra]]
    assert installed and not [r for r in installed if r.split('>')[0].split('=')[0].split('[')[0]
                              .startswith(TEST_TOOLS)]
    assert all(any(r.startswith(tool) for r in available['test']) for tool in TEST_TOOLS)


def test_benchmarks_and_reports_write_under_out_by_default():
    for path in sorted((REPO / 'benchmarks').glob('*.py')):
        text = path.read_text()
        assert "/ 'results'" not in text, f'{path.name} writes into benchmarks/results by default'
    cli = (REPO / 'feeder_sim' / 'cli.py').read_text()
    defaults = re.findall(r"'--out', default='([^']+)'", cli)
    assert defaults and all(d.startswith('out/') for d in defaults)


def test_default_outputs_are_ignored_by_git():
    # what the default outputs write is ignored by git
    out = subprocess.run(['git', 'check-ignore', 'out/bench/pile.json', 'out/stability/x.json',
                          'run.mcap', 'run.rrd'], cwd=REPO, capture_output=True, text=True)
    if out.returncode == 128:          # not a git checkout (an sdist): nothing to check
        return
    assert len(out.stdout.split()) == 4
