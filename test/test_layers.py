"""The package's import contract, read from the source (every import, at any depth of a module).

Layers go one way: compiled -> model -> contact -> stepping -> simulator -> output -> run ->
reports, ros, studies -> cli. Inside compiled/ (the numba support) too: cache -> progress, ahead
-> jit -> arena, and nothing else of the package. The physics layers import no ROS, MCAP,
plotting, replay or distributed-computing package; no stepping method imports another; output/
and ros/ never reach into a stepper; the node does not import the CLI's run loop. No import
cycle anywhere (imports for type checkers only excepted).
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'feeder_sim'

RANK = {'compiled': 0, 'model': 1, 'contact': 2, 'stepping': 3, 'simulator': 4, 'output': 5,
        'run': 6, 'reports': 7, 'ros': 7, 'studies': 7, 'cli': 8}
PHYSICS = ('model', 'contact', 'stepping')
FORBIDDEN_IN_PHYSICS = ('rclpy', 'mcap', 'mcap_ros2', 'matplotlib', 'rerun', 'dask',
                        'distributed', 'pyarrow', 'rosgraph_msgs', 'geometry_msgs',
                        'sensor_msgs', 'std_msgs', 'visualization_msgs', 'diagnostic_msgs')
METHODS = ('time_stepping', 'impulse_based', 'event_driven')


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob('*.py')):
        parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
        if parts[-1] == '__init__':
            parts = parts[:-1]
        out['.'.join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == 'TYPE_CHECKING'
            or isinstance(test, ast.Attribute) and test.attr == 'TYPE_CHECKING')


def _import_statements(tree: ast.AST, type_checking: bool = True):
    """Every import statement at any depth; without those under ``if TYPE_CHECKING:`` (whose
    ``else:`` runs) unless ``type_checking``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif not type_checking and isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
        else:
            stack.extend(ast.iter_child_nodes(node))


def _imported(name: str, path: Path, type_checking: bool = True) -> list[tuple[str, list[str]]]:
    """(absolute module, names taken from it, [] for ``import module``) of each import of
    ``name`` (relative imports resolved)."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = []
    for node in _import_statements(ast.parse(path.read_text(), str(path)), type_checking):
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names]
        else:
            base = node.module or ''
            if node.level:
                up = package.split('.')
                base = '.'.join(up[:len(up) - node.level + 1] + ([base] if base else []))
            found.append((base, [a.name for a in node.names]))
    return found


def _imports(name: str, path: Path) -> set[str]:
    """Absolute names of every module ``name`` imports (relative imports resolved)."""
    found = set()
    for base, names in _imported(name, path):
        found.add(base)
        # `from feeder_sim.x import y` may name a submodule y
        found.update(f'{base}.{n}' for n in names)
    return found


MODULES = _modules()
IMPORTS = {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(module: str) -> str | None:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 and parts[0] == 'feeder_sim' else None


def _own(module: str) -> set[str]:
    """feeder_sim modules (not names inside them) that ``module`` imports."""
    return {m for m in IMPORTS[module] if m in MODULES and m != 'feeder_sim'}


def test_every_module_has_a_layer():
    assert {_layer(m) for m in MODULES} - {None} <= set(RANK)


@pytest.mark.parametrize('module', [m for m in MODULES if _layer(m)])
def test_imports_go_one_way(module):
    rank = RANK[_layer(module)]
    upward = sorted(m for m in _own(module) if _layer(m) and RANK[_layer(m)] > rank)
    assert not upward, f'{module} imports a higher layer: {upward}'


@pytest.mark.parametrize('module', [m for m in MODULES
                                    if _layer(m) in PHYSICS + ('compiled',)])
def test_physics_imports_no_ros_mcap_plotting_or_dask(module):
    bad = sorted(m for m in IMPORTS[module] if m.split('.')[0] in FORBIDDEN_IN_PHYSICS)
    assert not bad, f'{module} imports {bad}'


# feeder_sim.model.scene: each module imports only those ranked below it (never the package)
SCENE = 'feeder_sim.model.scene'
SCENE_RANK = {'errors': 0, 'specs': 0, 'expressions': 1, 'fields': 2, 'outlines': 3, 'parse': 4,
              'files': 5}


def test_every_scene_module_has_a_rank():
    assert {m.rpartition('.')[2] for m in MODULES if m.startswith(SCENE + '.')} == set(SCENE_RANK)


@pytest.mark.parametrize('module', [m for m in MODULES if m.startswith(SCENE + '.')])
def test_scene_modules_import_one_way(module):
    rank = SCENE_RANK[module.rpartition('.')[2]]
    inside = {m for m in _own(module) if m == SCENE or m.startswith(SCENE + '.')}
    bad = sorted(m for m in inside if m == SCENE or SCENE_RANK[m.rpartition('.')[2]] >= rank)
    assert not bad, f'{module} imports the package or a module not below it: {bad}'


# feeder_sim.compiled: each module imports only those ranked below it, and nothing else of the
# package (the package itself imports nothing)
COMPILED = 'feeder_sim.compiled'
COMPILED_RANK = {'cache': 0, 'progress': 1, 'ahead': 1, 'jit': 2, 'arena': 3}


def test_every_compiled_module_has_a_rank():
    assert {m.rpartition('.')[2] for m in MODULES if m.startswith(COMPILED + '.')} == \
        set(COMPILED_RANK)
    assert IMPORTS[COMPILED] == set()


@pytest.mark.parametrize('module', [m for m in MODULES if m.startswith(COMPILED + '.')])
def test_compiled_modules_import_one_way_and_nothing_else_of_the_package(module):
    rank = COMPILED_RANK[module.rpartition('.')[2]]
    outside = sorted(m for m in _own(module) if m != COMPILED and not m.startswith(COMPILED + '.'))
    assert not outside, f'{module} imports the package beyond compiled/: {outside}'
    bad = sorted(m for m in _own(module) if m.startswith(COMPILED + '.')
                 and COMPILED_RANK[m.rpartition('.')[2]] >= rank)
    assert not bad, f'{module} imports a compiled module not below it: {bad}'


def _runtime_own(module: str) -> set[str]:
    """The feeder_sim modules ``module`` makes Python import when it runs: at any depth of it,
    but not for type checkers only (``if TYPE_CHECKING:``). ``from x import y`` imports
    submodule x.y if there is one, else module x (a package's ``__init__``)."""
    found = set()
    for base, names in _imported(module, MODULES[module], type_checking=False):
        subs = {f'{base}.{n}' for n in names} & MODULES.keys()
        found |= subs if subs and len(subs) == len(names) else subs | {base}
    return {m for m in found if m in MODULES and m != module}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` (node -> successors) as [a, b, ..., a], or None if it has none."""
    done: set[str] = set()
    for root in sorted(graph):
        if root in done:
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                stack.pop()
                done.add(path.pop())
            elif nxt in path:
                return path[path.index(nxt):] + [nxt]
            elif nxt not in done:
                path.append(nxt)
                stack.append(iter(sorted(graph.get(nxt, ()))))
    return None


def test_no_import_cycle_in_the_package():
    graph = {m: _runtime_own(m) for m in MODULES}
    cycle = _cycle(graph)
    assert cycle is None, f'import cycle: {" -> ".join(cycle)}'


def test_the_cycle_check_sees_cycles_and_skips_type_checking_imports():
    assert _cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == ['a', 'b', 'c', 'a']
    assert _cycle({'a': {'b', 'c'}, 'b': {'c'}, 'c': set()}) is None
    assert _cycle({'a': {'a'}}) == ['a', 'a']
    # the simulator's rooms name Simulator for type checkers only: no cycle through them
    room = 'feeder_sim.simulator.energy_check'
    assert 'feeder_sim.simulator.simulator' in _own(room)
    assert 'feeder_sim.simulator.simulator' not in _runtime_own(room)
    assert room in _runtime_own('feeder_sim.simulator.simulator')
    # function-level imports count (the CLI imports most of the package inside its commands)
    assert 'feeder_sim.compiled.jit' in _runtime_own('feeder_sim.cli')


def _method_of(module: str) -> str | None:
    parts = module.split('.')
    if parts[:2] == ['feeder_sim', 'stepping'] and len(parts) > 2 and parts[2] in METHODS:
        return parts[2]
    return None


@pytest.mark.parametrize('module', [m for m in MODULES if _method_of(m)])
def test_no_stepping_method_imports_another(module):
    mine = _method_of(module)
    others = sorted(m for m in _own(module) if _method_of(m) not in (None, mine))
    assert not others, f'{module} imports another stepping method: {others}'


@pytest.mark.parametrize('module', [m for m in MODULES if _layer(m) in ('output', 'ros')])
def test_output_and_ros_never_reach_into_a_stepper(module):
    # the package's face (STEPPERS: each method's policy) is theirs to read
    inner = sorted(m for m in _own(module)
                   if _layer(m) == 'stepping' and m != 'feeder_sim.stepping')
    assert not inner, f'{module} imports stepping internals: {inner}'


# Where a method's name may decide what happens: the methods themselves, the scene's list of
# methods (its step rules) and the reports, whose experiments compare the methods by name.
NAMED_METHODS_ALLOWED = ('stepping', 'model', 'reports')


@pytest.mark.parametrize('module', [m for m in MODULES
                                    if _layer(m) not in NAMED_METHODS_ALLOWED])
def test_no_branch_on_a_method_name_outside_stepping(module):
    """What differs between methods is their policy (``STEPPERS[name].fixed_steps``, ...),
    never a comparison with a method's name."""
    branches = []
    for node in ast.walk(ast.parse(MODULES[module].read_text())):
        if isinstance(node, ast.Compare):
            named = [n for n in ast.walk(node)
                     if isinstance(n, ast.Constant) and n.value in METHODS]
            if named:
                branches.append(f'line {node.lineno}: {named[0].value!r}')
    assert not branches, f'{module} branches on a method name: {branches}'


def test_the_node_does_not_import_the_cli_run_loop():
    for module in MODULES:
        if _layer(module) == 'ros':
            assert not _own(module) & {'feeder_sim.run', 'feeder_sim.cli'}, module


def test_the_contract_is_checked_on_real_imports():
    # the checker itself: a known import of each kind is seen
    assert 'feeder_sim.stepping.protocol' in _own('feeder_sim.stepping.time_stepping.stepper')
    assert 'rclpy' in IMPORTS['feeder_sim.ros.node']
    assert 'feeder_sim.output.frames' in _own('feeder_sim.ros.node')
