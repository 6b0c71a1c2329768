"""Tests of feeder_sim.model.scene: parsing, defaults, decomposition, one test per bad input.

Numbers read from YAML are compared exactly (the parser must not change them); derived mass
properties to 1e-12 relative.
"""

import copy
import math
from pathlib import Path
import pickle
import re

import numpy as np
import pytest
import yaml

import feeder_sim
from feeder_sim.model import geometry
from feeder_sim.model.scene import (
    BodySpec,
    load_scene,
    parse_scene,
    Scene,
    scene_dirs,
    scene_to_dict,
    SceneError,
    shipped_scenes,
    SolverSpec,
    Vibration,
)

REL = 1e-12

# Example 1: every key of the format, as in docs/interfaces.md.
FULL = """\
name: incline_stick            # free text
gravity: [0.0, -9.81]
track: track
solver:
  method: event_driven
  time_step: 1.0e-4
  friction_impulse: true
  tolerance: 1.0e-9
bodies:
  - name: track
    type: kinematic
    polygon: [[-0.5, -0.01], [0.5, -0.01], [0.5, 0.0], [-0.5, 0.0]]
    pose: [0.0, 0.0, 0.0524]
    mu_static: 0.5
    mu_dynamic: 0.4
    restitution: 0.0
    vibration:
      amplitude: 1.0e-3
      frequency: 50.0
      angle: 0.349
      phase: 0.0
  - name: part_0
    type: dynamic
    polygon: [[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005], [-0.01, 0.005]]
    mass: 0.01
    pose: [0.0, 0.005, 0.0524]
    velocity: [0.0, 0.0, 0.0]
    mu_static: 0.5
    mu_dynamic: 0.4
    restitution: 0.0
"""

# Example 2: only the required keys; everything else takes its default.
MINIMAL = """\
bodies:
  - name: floor
    type: static
    polygon: [[-0.1, -0.01], [0.1, -0.01], [0.1, 0], [-0.1, 0]]
    pose: [0, 0, 0]
  - name: box
    type: dynamic
    polygon: [[0, 0], [0.02, 0], [0.02, 0.01], [0, 0.01]]
    density: 2.5
    pose: [0, 0.001, 0]
"""

# Example 3: concave parts, one as a `polygon:` outline (a cup, 20 x 12 mm, 2 mm walls) and one
# as `polygons:` pieces (an L); exponents without a dot; an empty solver block.
CUPS = """\
name: cups on a tray
solver:
  # all defaults
bodies:
  - name: tray
    type: kinematic
    polygon: [[-0.2, -0.01], [0.2, -0.01], [0.2, 0], [-0.2, 0]]
    pose: [0, 0, 0]
    mu_static: 0.3
    vibration: {amplitude: 5e-5, frequency: 100, angle: 0.5236}
  - name: cup
    type: dynamic
    polygon: [[0, 0], [0.02, 0], [0.02, 0.012], [0.018, 0.012], [0.018, 0.002],
              [0.002, 0.002], [0.002, 0.012], [0, 0.012]]
    mass: 3e-3
    pose: [-0.01, 0.0, 0.0]
    velocity: [0.01, 0, 0.5]
  - name: ell
    type: dynamic
    polygons:
      - [[0, 0], [0.02, 0], [0.02, 0.01], [0, 0.01]]
      - [[0, 0.01], [0.01, 0.01], [0.01, 0.03], [0, 0.03]]
    density: 1.2
    pose: [0.05, 0.0, 0.0]
    restitution: 0.25
"""


def write(tmp_path: Path, text: str, name: str = 'scene.yaml') -> Path:
    path = tmp_path / name
    path.write_text(text, encoding='utf-8')
    return path


def readonly(arr: np.ndarray) -> bool:
    return not arr.flags.writeable


# ---------------------------------------------------------------- valid scenes

def test_full_example_parses_with_exact_values(tmp_path):
    scene = load_scene(write(tmp_path, FULL, 'track.yaml'))
    assert scene.name == 'incline_stick'
    assert scene.source.endswith('track.yaml')
    np.testing.assert_array_equal(scene.gravity, [0.0, -9.81])
    assert scene.solver == SolverSpec('event_driven', 1.0e-4, True, 1.0e-9)
    assert scene.track == 'track'
    track, part = scene.bodies
    assert (track.name, track.type, part.name, part.type) == ('track', 'kinematic',
                                                              'part_0', 'dynamic')
    np.testing.assert_array_equal(track.outlines[0],
                                  [[-0.5, -0.01], [0.5, -0.01], [0.5, 0.0], [-0.5, 0.0]])
    assert len(track.pieces) == 1
    np.testing.assert_array_equal(track.pieces[0], track.outlines[0])
    np.testing.assert_array_equal(track.pose, [0.0, 0.0, 0.0524])
    np.testing.assert_array_equal(track.velocity, [0.0, 0.0, 0.0])
    assert (track.mass, track.density) == (None, None)
    assert (track.mu_static, track.mu_dynamic, track.restitution) == (0.5, 0.4, 0.0)
    assert track.vibration == Vibration(amplitude=1.0e-3, frequency=50.0, angle=0.349, phase=0.0)
    assert track.mass_properties is None
    np.testing.assert_array_equal(part.pieces[0], [[-0.01, -0.005], [0.01, -0.005],
                                                   [0.01, 0.005], [-0.01, 0.005]])
    np.testing.assert_array_equal(part.pose, [0.0, 0.005, 0.0524])
    assert (part.mass, part.density, part.vibration) == (0.01, None, None)
    assert (part.mu_static, part.mu_dynamic, part.restitution) == (0.5, 0.4, 0.0)
    props = part.mass_properties
    assert props.mass == 0.01
    assert props.inertia == pytest.approx(0.01 * (0.02 ** 2 + 0.01 ** 2) / 12, rel=REL)
    np.testing.assert_allclose(props.centroid, [0, 0], rtol=0, atol=1e-17)


def test_types_are_plain_python():
    scene = parse_scene(yaml.safe_load(FULL))
    part = scene.bodies[1]
    assert type(part.mass) is float and type(part.mu_static) is float
    assert type(scene.solver.friction_impulse) is bool
    assert part.pose.dtype == np.float64 and part.pieces[0].dtype == np.float64


def test_defaults_are_applied(tmp_path):
    scene = load_scene(write(tmp_path, MINIMAL, 'minimal_box.yaml'))
    assert scene.name == 'minimal_box'                    # the file stem
    np.testing.assert_array_equal(scene.gravity, [0.0, -9.81])
    assert scene.solver == SolverSpec()
    assert scene.solver == SolverSpec('event_driven', 1e-4, True, 1e-9)
    assert scene.track == 'floor'                          # first non-dynamic body
    box = scene.body('box')
    np.testing.assert_array_equal(box.velocity, [0.0, 0.0, 0.0])
    assert (box.mu_static, box.mu_dynamic, box.restitution) == (0.0, 0.0, 0.0)
    assert (box.mass, box.density, box.vibration) == (None, 2.5, None)
    assert box.mass_properties.mass == pytest.approx(2.5 * 0.02 * 0.01, rel=REL)
    np.testing.assert_allclose(box.mass_properties.centroid, [0.01, 0.005], rtol=REL)
    assert parse_scene(yaml.safe_load(MINIMAL)).name == 'unnamed'


def test_mu_dynamic_defaults_to_mu_static_and_phase_to_zero(tmp_path):
    scene = load_scene(write(tmp_path, CUPS))
    tray = scene.body('tray')
    assert (tray.mu_static, tray.mu_dynamic) == (0.3, 0.3)
    assert tray.vibration == Vibration(5e-5, 100.0, 0.5236, 0.0)
    assert scene.solver == SolverSpec()
    assert scene.track == 'tray'                            # the vibrating kinematic body


def test_polygon_cup_is_decomposed(tmp_path):
    scene = load_scene(write(tmp_path, CUPS))
    cup = scene.body('cup')
    outline = [[0, 0], [0.02, 0], [0.02, 0.012], [0.018, 0.012], [0.018, 0.002],
               [0.002, 0.002], [0.002, 0.012], [0, 0.012]]
    assert len(cup.outlines) == 1
    np.testing.assert_array_equal(cup.outlines[0], outline)
    assert 2 <= len(cup.pieces) <= 5
    for piece in cup.pieces:
        assert geometry.is_convex(piece)
    area = 20 * 2 + 2 * (2 * 10)                            # mm^2: floor + two walls
    assert sum(geometry.polygon_area(p) for p in cup.pieces) == pytest.approx(area * 1e-6,
                                                                             rel=REL)
    # Pieces stay in the body frame of the file: not shifted to the centroid.
    np.testing.assert_array_equal(np.min(np.vstack(cup.pieces), axis=0), [0.0, 0.0])
    rect_centroids = np.array([[10, 1], [1, 7], [19, 7]]) * 1e-3
    rect_areas = np.array([40, 20, 20])
    centroid = rect_areas @ rect_centroids / rect_areas.sum()
    np.testing.assert_allclose(cup.mass_properties.centroid, centroid, rtol=0, atol=REL * 0.02)
    assert cup.mass_properties.mass == 3e-3
    np.testing.assert_array_equal(cup.velocity, [0.01, 0.0, 0.5])


def test_polygons_pieces_are_kept(tmp_path):
    ell = load_scene(write(tmp_path, CUPS)).body('ell')
    assert len(ell.pieces) == 2 and len(ell.outlines) == 2
    np.testing.assert_array_equal(ell.pieces[1], [[0, 0.01], [0.01, 0.01], [0.01, 0.03],
                                                  [0, 0.03]])
    props = ell.mass_properties
    assert props.mass == pytest.approx(1.2 * (0.02 * 0.01 + 0.01 * 0.02), rel=REL)
    assert ell.restitution == 0.25


def test_collinear_vertices_are_dropped_from_pieces():
    data = yaml.safe_load(MINIMAL)
    data['bodies'][1]['polygons'] = [[[0, 0], [0.01, 0], [0.02, 0], [0.02, 0.01], [0, 0.01]]]
    del data['bodies'][1]['polygon']
    box = parse_scene(data).body('box')
    assert len(box.outlines[0]) == 5
    np.testing.assert_array_equal(box.pieces[0], [[0, 0], [0.02, 0], [0.02, 0.01], [0, 0.01]])


def test_an_outline_is_checked_once_however_many_bodies_have_it(monkeypatch):
    # a bowl's load is many parts of one shape: its geometry is checked and decomposed once,
    # and a bad one is still reported at each body's own key
    calls = []
    simple = geometry.is_simple
    monkeypatch.setattr(geometry, 'is_simple', lambda v: calls.append(1) or simple(v))
    cup = [[0, 0], [0.021, 0], [0.021, 0.013], [0.019, 0.013], [0.019, 0.002],
           [0.002, 0.002], [0.002, 0.013], [0, 0.013]]
    data = yaml.safe_load(FULL)
    part = data['bodies'][1]
    data['bodies'][1:] = [{**part, 'name': f'cup_{k}', 'polygon': cup,
                           'pose': [-0.4 + 0.03 * k, 0.1, 0.0]} for k in range(30)]
    scene = parse_scene(data)
    assert len(calls) <= 2 * 2          # two outlines (track, cup): the check, the decomposition
    assert all(len(b.pieces) == 3 for b in scene.bodies[1:])
    np.testing.assert_array_equal(scene.bodies[5].pieces[1], scene.bodies[20].pieces[1])
    for k in (3, 17):
        bad = copy.deepcopy(data)
        bad['bodies'][k]['polygon'] = cup[::-1]      # clockwise, seen before at another key
        with pytest.raises(SceneError) as err:
            parse_scene(bad)
        assert err.value.path == f'bodies[{k}].polygon'
        assert 'counter-clockwise' in err.value.message


def test_arrays_are_read_only(tmp_path):
    scene = load_scene(write(tmp_path, CUPS))
    arrays = [scene.gravity]
    for body in scene.bodies:
        arrays += [body.pose, body.velocity, *body.pieces, *body.outlines]
    assert all(readonly(a) for a in arrays)
    with pytest.raises(ValueError):
        scene.bodies[1].pose[0] = 1.0
    with pytest.raises(AttributeError):
        scene.name = 'other'


def test_input_lists_are_copied():
    data = yaml.safe_load(MINIMAL)
    scene = parse_scene(data)
    data['bodies'][1]['pose'][0] = 99.0
    assert scene.body('box').pose[0] == 0.0


@pytest.mark.parametrize('text', [FULL, MINIMAL, CUPS], ids=['full', 'minimal', 'cups'])
def test_scene_to_dict_round_trips(text, tmp_path):
    scene = load_scene(write(tmp_path, text))
    data = scene_to_dict(scene)
    assert parse_scene(data, scene.source) == scene
    # Through YAML text too, as it is recorded in logs.
    assert parse_scene(yaml.safe_load(yaml.safe_dump(data)), scene.source) == scene


def test_scene_without_dynamic_bodies_is_allowed():
    data = yaml.safe_load(FULL)
    del data['bodies'][1]
    scene = parse_scene(data)
    assert [b.type for b in scene.bodies] == ['kinematic']


@pytest.mark.parametrize('types, vibrating, expected', [
    (['static', 'kinematic', 'dynamic'], [1], 'b1'),   # the vibrating kinematic body
    (['dynamic', 'kinematic', 'static'], [], 'b1'),    # else the first non-dynamic body
    (['dynamic', 'dynamic'], [], None),                # else none
])
def test_default_track(types, vibrating, expected):
    square = [[0, 0], [1, 0], [1, 1], [0, 1]]
    bodies = []
    for k, kind in enumerate(types):
        body = {'name': f'b{k}', 'type': kind, 'polygon': square, 'pose': [3 * k, 0, 0]}
        if kind == 'dynamic':
            body['mass'] = 1.0
        if k in vibrating:
            body['vibration'] = {'amplitude': 1e-4, 'frequency': 60, 'angle': 0.3}
        bodies.append(body)
    assert parse_scene({'bodies': bodies}).track == expected


def test_track_may_be_null_or_any_body():
    data = yaml.safe_load(FULL)
    data['track'] = None
    assert parse_scene(data).track is None
    data['track'] = 'part_0'
    assert parse_scene(data).track == 'part_0'


def test_yaml_12_floats_and_null_blocks(tmp_path):
    text = FULL.replace('1.0e-3', '1e-3').replace('1.0e-4', '1E-4')
    scene = load_scene(write(tmp_path, text))
    assert scene.bodies[0].vibration.amplitude == 1e-3
    assert scene.solver.time_step == 1e-4
    data = yaml.safe_load(FULL)
    data['bodies'][0]['vibration'] = None
    assert parse_scene(data).bodies[0].vibration is None


# ---------------------------------------------------------------- bad input: data

def _keys(path: str) -> list:
    return [int(k) if k.isdigit() else k for k in re.findall(r'[^.\[\]]+', path)]


def _set(data, path, value):
    *parents, last = _keys(path)
    for k in parents:
        data = data[k]
    data[last] = value


def _del(data, path):
    *parents, last = _keys(path)
    for k in parents:
        data = data[k]
    del data[last]


DEL = object()
CW = [[-0.01, 0.005], [0.01, 0.005], [0.01, -0.005], [-0.01, -0.005]]
BOW_TIE = [[0, 0], [0.01, 0.01], [0.01, 0], [0, 0.01]]
CROSSING = [[0, 0], [0.02, 0], [0.02, 0.02], [0, 0.02], [0.03, 0.01]]
L_PIECE = [[0, 0], [0.02, 0], [0.02, 0.01], [0.01, 0.01], [0.01, 0.03], [0, 0.03]]
SQUARE = [[0, 0], [0.01, 0], [0.01, 0.01], [0, 0.01]]

# (id, {path: new value | DEL}, expected .path, fragments the message must contain)
BAD = [
    # unknown keys, at every level, with a suggestion and the allowed keys
    ('unknown top key', {'gravty': [0, -9.81]}, 'gravty',
     ["unknown key 'gravty'", "did you mean 'gravity'?",
      'allowed keys: name, parameters, gravity']),
    ('unknown body key', {'bodies[1].mas': 0.01}, 'bodies[1].mas',
     ["did you mean 'mass'?", 'allowed keys:', 'density']),
    ('unknown solver key', {'solver.time_stp': 1e-3}, 'solver.time_stp',
     ["did you mean 'time_step'?"]),
    ('unknown vibration key', {'bodies[0].vibration.amplitud': 1e-3},
     'bodies[0].vibration.amplitud', ["did you mean 'amplitude'?"]),
    ('alias key', {'bodies[1].mu': 0.3}, 'bodies[1].mu', ["did you mean 'mu_static'?"]),
    ('non-text key', {'bodies[1].7': 1}, 'bodies[1]', ['keys must be text']),
    # wrong types
    ('bool mass', {'bodies[1].mass': True}, 'bodies[1].mass',
     ['expected a number (kg) in [1e-09, 1e+06]', 'true (a boolean)']),
    ('bool in vector', {'gravity': [0, False]}, 'gravity[1]', ['expected a number']),
    ('quoted number', {'bodies[1].mass': '0.01'}, 'bodies[1].mass',
     ['YAML read it as text: remove any quotes']),
    ('text friction', {'bodies[1].mu_static': 'high'}, 'bodies[1].mu_static',
     ['expected a number', "the text 'high'"]),
    ('mapping pose', {'bodies[1].pose': {'x': 0}}, 'bodies[1].pose',
     ['expected a list of 3 numbers [x, y, theta]']),
    ('null value', {'bodies[1].mass': None}, 'bodies[1].mass', ["'mass' has no value"]),
    ('name not text', {'bodies[1].name': 5}, 'bodies[1].name', ['expected text', 'quotes']),
    ('empty name', {'bodies[1].name': '  '}, 'bodies[1].name', ['expected non-empty text']),
    ('scene name not text', {'name': ['a']}, 'name', ['expected text']),
    ('bool friction_impulse', {'solver.friction_impulse': 1}, 'solver.friction_impulse',
     ['expected true or false']),
    ('unknown method', {'solver.method': 'event-driven'}, 'solver.method',
     ["did you mean 'event_driven'?", 'event_driven, time_stepping, impulse_based']),
    ('unknown type', {'bodies[1].type': 'dynamc'}, 'bodies[1].type',
     ["did you mean 'dynamic'?", 'static, kinematic, dynamic']),
    ('body not a mapping', {'bodies[1]': 'part_0'}, 'bodies[1]', ['expected a mapping']),
    ('bodies not a list', {'bodies': {'name': 'x'}}, 'bodies', ['non-empty list of bodies']),
    ('vibration not a mapping', {'bodies[0].vibration': 50.0}, 'bodies[0].vibration',
     ['expected a mapping with the keys amplitude, frequency, angle, phase']),
    # non-finite numbers
    ('nan restitution', {'bodies[1].restitution': math.nan}, 'bodies[1].restitution',
     ['only finite numbers']),
    ('inf gravity', {'gravity': [0.0, -math.inf]}, 'gravity[1]', ['only finite numbers']),
    ('nan vertex', {'bodies[1].polygon[2][0]': math.nan}, 'bodies[1].polygon[2][0]',
     ['finite']),
    # wrong lengths
    ('short pose', {'bodies[1].pose': [0, 0]}, 'bodies[1].pose',
     ['expected 3 numbers [x, y, theta]', 'a list of 2 items']),
    ('long gravity', {'gravity': [0, -9.81, 0]}, 'gravity', ['expected 2 numbers']),
    ('short velocity', {'bodies[1].velocity': [0]}, 'bodies[1].velocity',
     ['expected 3 numbers [vx, vy, omega]']),
    ('3d vertex', {'bodies[1].polygon[2]': [0.01, 0.005, 0]}, 'bodies[1].polygon[2]',
     ['expected 2 numbers [x, y]']),
    ('two vertices', {'bodies[1].polygon': [[0, 0], [1, 0]]}, 'bodies[1].polygon',
     ['at least 3']),
    # bad polygons
    ('bow-tie', {'bodies[1].polygon': BOW_TIE}, 'bodies[1].polygon',
     ['polygon is self-intersecting (edges 0 and 2 cross)',
      'give the outline as a simple counter-clockwise polygon']),
    ('crossing', {'bodies[1].polygon': CROSSING}, 'bodies[1].polygon',
     ['self-intersecting (edges 1 and 3 cross)']),
    ('repeated vertex', {'bodies[1].polygon': [[0, 0], [0.02, 0], [0.01, 0.01], [0.02, 0.02],
                                               [0, 0.02], [0.01, 0.01]]},
     'bodies[1].polygon', ['vertices 2 and 5 coincide', 'simple counter-clockwise']),
    ('closed outline', {'bodies[1].polygon': SQUARE + [[0, 0]]}, 'bodies[1].polygon',
     ['do not close the outline']),
    ('collinear', {'bodies[1].polygon': [[0, 0], [0.01, 0], [0.02, 0]]}, 'bodies[1].polygon',
     ['zero area']),
    ('clockwise', {'bodies[1].polygon': CW}, 'bodies[1].polygon',
     ['vertices must be counter-clockwise; reverse the list']),
    ('non-convex piece', {'bodies[1].polygon': DEL, 'bodies[1].polygons': [SQUARE, L_PIECE]},
     'bodies[1].polygons[1]', ['not convex', 'vertex 3', 'split it into convex pieces']),
    ('clockwise piece', {'bodies[1].polygon': DEL, 'bodies[1].polygons': [CW]},
     'bodies[1].polygons[0]', ['counter-clockwise; reverse the list']),
    ('self-intersecting piece', {'bodies[1].polygon': DEL, 'bodies[1].polygons': [BOW_TIE]},
     'bodies[1].polygons[0]', ['piece is self-intersecting']),
    ('overlapping pieces', {'bodies[1].polygon': DEL,
                            'bodies[1].polygons': [SQUARE, [[0.005, 0], [0.015, 0],
                                                            [0.015, 0.01], [0.005, 0.01]]]},
     'bodies[1].polygons', ['pieces 0 and 1 overlap']),
    ('empty polygons', {'bodies[1].polygon': DEL, 'bodies[1].polygons': []},
     'bodies[1].polygons', ['non-empty list of convex pieces']),
    ('polygon and polygons', {'bodies[1].polygons': [SQUARE]}, 'bodies[1]',
     ['either `polygon`', 'not both']),
    ('no shape', {'bodies[1].polygon': DEL}, 'bodies[1].polygon',
     ['missing the shape', '`polygon: [[x, y], ...]`']),
    # mass and density
    ('no mass', {'bodies[1].mass': DEL}, 'bodies[1].mass',
     ['a dynamic body needs `mass` (kg) or `density` (kg/m^2)']),
    ('mass and density', {'bodies[1].density': 50.0}, 'bodies[1].density',
     ['either `mass` (kg) or `density` (kg/m^2), not both']),
    ('zero mass', {'bodies[1].mass': 0}, 'bodies[1].mass',
     ['0 is out of range', 'expected a number (kg) in [1e-09, 1e+06]']),
    ('negative density', {'bodies[1].mass': DEL, 'bodies[1].density': -1.0},
     'bodies[1].density', ['-1 is out of range', 'in [1e-06, 1e+06]']),
    ('mass on kinematic', {'bodies[0].mass': 1.0}, 'bodies[0].mass',
     ['prescribed', 'remove `mass`']),
    ('density on static', {'bodies[0].type': 'static', 'bodies[0].vibration': DEL,
                           'bodies[0].density': 1.0}, 'bodies[0].density',
     ['a static body never moves', 'remove `density`']),
    # out-of-range values
    ('mu_static too large', {'bodies[1].mu_static': 11.0}, 'bodies[1].mu_static',
     ['11 is out of range', 'in [0, 10]']),
    ('negative mu', {'bodies[1].mu_static': -0.1}, 'bodies[1].mu_static', ['in [0, 10]']),
    ('mu_dynamic above mu_static', {'bodies[1].mu_dynamic': 0.6}, 'bodies[1].mu_dynamic',
     ['mu_dynamic (0.6) must not exceed mu_static (0.5)', '0 <= mu_dynamic <= mu_static']),
    ('mu_dynamic without mu_static', {'bodies[1].mu_static': DEL}, 'bodies[1].mu_dynamic',
     ['mu_static (0, the default)']),
    ('restitution above 1', {'bodies[1].restitution': 1.5}, 'bodies[1].restitution',
     ['in [0, 1]']),
    ('amplitude too large', {'bodies[0].vibration.amplitude': 0.5},
     'bodies[0].vibration.amplitude', ['in [0, 0.1]', 'typically']),
    ('negative amplitude', {'bodies[0].vibration.amplitude': -1e-3},
     'bodies[0].vibration.amplitude', ['in [0, 0.1]']),
    ('frequency too large', {'bodies[0].vibration.frequency': 5000},
     'bodies[0].vibration.frequency', ['(Hz) in [0, 1000]']),
    ('zero time step', {'solver.time_step': 0.0}, 'solver.time_step', ['(s) in [1e-07, 0.1]']),
    ('tiny time step', {'solver.time_step': 1e-300}, 'solver.time_step',
     ['in [1e-07, 0.1]', '1e7 per simulated second']),
    ('denormal amplitude', {'bodies[0].vibration.amplitude': 1e-310},
     'bodies[0].vibration.amplitude', ['below the smallest the physics resolves', 'give 0']),
    ('denormal frequency', {'bodies[0].vibration.frequency': 5e-324},
     'bodies[0].vibration.frequency', ['below the smallest the physics resolves (0.001 Hz)']),
    ('huge gravity', {'gravity': [0.0, -1e300]}, 'gravity[1]', ['in [-10000, 10000]']),
    ('huge velocity', {'bodies[1].velocity': [1e300, 0.0, 0.0]}, 'bodies[1].velocity[0]',
     ['in [-1000, 1000]']),
    ('huge spin', {'bodies[1].velocity': [0.0, 0.0, 1e300]}, 'bodies[1].velocity[2]',
     ['in [-100000, 100000]']),
    ('huge pose angle', {'bodies[1].pose': [0.0, 0.0, 1e16]}, 'bodies[1].pose[2]',
     ['in [-1000, 1000]']),
    ('far pose', {'bodies[1].pose': [1e300, 0.0, 0.0]}, 'bodies[1].pose[0]',
     ['in [-10000, 10000]']),
    ('tiny mass', {'bodies[1].mass': 1e-300}, 'bodies[1].mass', ['in [1e-09, 1e+06]']),
    ('huge mass', {'bodies[1].mass': 1e300}, 'bodies[1].mass', ['in [1e-09, 1e+06]']),
    ('tiny outline', {'bodies[1].polygon': [[0, 0], [1e-9, 0], [1e-9, 1e-9], [0, 1e-9]]},
     'bodies[1].polygon', ['m across; outlines must span at least 1e-06 m']),
    ('sliver piece', {'bodies[0].polygon': [[-0.5, -1e-9], [0.5, -1e-9], [0.5, 0.0],
                                             [-0.5, 0.0]]},
     'bodies[0].polygon', ['m thin (at least 1e-06 m)', 'thicken the sliver']),
    ('time step too large', {'solver.time_step': 0.5}, 'solver.time_step', ['in [1e-07, 0.1]']),
    ('tolerance too large', {'solver.tolerance': 0.1}, 'solver.tolerance', ['in (0, 0.01]']),
    ('missing amplitude', {'bodies[0].vibration.amplitude': DEL},
     'bodies[0].vibration.amplitude', ["missing required key 'amplitude'"]),
    # cross-field rules
    ('duplicate names', {'bodies[1].name': 'track'}, 'bodies[1].name',
     ["duplicate body name 'track'", 'bodies[0]', 'unique']),
    ('vibration on dynamic', {'bodies[1].vibration': {'amplitude': 1e-3, 'frequency': 50,
                                                      'angle': 0.3}},
     'bodies[1].vibration', ['only kinematic bodies vibrate', 'dynamic']),
    ('vibration on static', {'bodies[0].type': 'static'}, 'bodies[0].vibration',
     ['only kinematic bodies vibrate']),
    ('velocity on kinematic', {'bodies[0].velocity': [0.1, 0, 0]}, 'bodies[0].velocity',
     ['[0, 0, 0]', 'vibration']),
    ('unknown track', {'track': 'trak'}, 'track',
     ["no body named 'trak'", "did you mean 'track'?", 'track, part_0']),
    # angles bounded as pose angles are: beyond 1000 rad sin/cos lose the direction
    ('huge drive angle', {'bodies[0].vibration.angle': 1e300}, 'bodies[0].vibration.angle',
     ['in [-1000, 1000]']),
    ('huge drive phase', {'bodies[0].vibration.phase': -2e3}, 'bodies[0].vibration.phase',
     ['in [-1000, 1000]']),
    # names become ROS frame ids and key paths
    ('name with a slash', {'bodies[1].name': 'a/b'}, 'bodies[1].name',
     ["'a/b' is not a body name: use letters, digits, _ and -"]),
    ('name with a newline', {'bodies[1].name': 'a\nb'}, 'bodies[1].name',
     ['is not a body name']),
    # structure
    ('no bodies key', {'bodies': DEL}, 'bodies', ["missing required key 'bodies'"]),
    ('empty bodies', {'bodies': []}, 'bodies', ['non-empty list']),
    ('missing pose', {'bodies[1].pose': DEL}, 'bodies[1].pose',
     ["missing required key 'pose'", '[x, y, theta]']),
    ('missing type', {'bodies[1].type': DEL}, 'bodies[1].type',
     ["missing required key 'type'", 'static, kinematic, dynamic']),
    ('solver not a mapping', {'solver': 'event_driven'}, 'solver', ['expected a mapping']),
]


@pytest.mark.parametrize('changes, path, fragments', [case[1:] for case in BAD],
                         ids=[case[0] for case in BAD])
def test_bad_input_is_rejected(changes, path, fragments):
    data = copy.deepcopy(yaml.safe_load(FULL))
    for key, value in changes.items():
        if value is DEL:
            _del(data, key)
        else:
            _set(data, key, value)
    with pytest.raises(SceneError) as info:
        parse_scene(data, 'track.yaml')
    err = info.value
    assert isinstance(err, ValueError)
    assert err.path == path
    assert err.source == 'track.yaml'
    for fragment in fragments:
        assert fragment in err.message, (fragment, err.message)
    prefix = f'track.yaml: {path}: ' if path else 'track.yaml: '
    assert str(err) == prefix + err.message


def test_message_reads_like_the_documented_example():
    data = yaml.safe_load(FULL)
    data['bodies'][1]['polygon'] = CROSSING
    with pytest.raises(SceneError) as info:
        parse_scene(data, 'track.yaml')
    assert str(info.value).startswith(
        'track.yaml: bodies[1].polygon: polygon is self-intersecting (edges 1 and 3 cross); '
        'give the outline as a simple counter-clockwise polygon')


@pytest.mark.parametrize('data, fragment', [
    ([1, 2], 'expected the top level of the file to be a mapping'),
    ('bodies', 'got the text'),
], ids=['list', 'text'])
def test_top_level_must_be_a_mapping(data, fragment):
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == ''
    assert fragment in info.value.message
    assert 'bodies' in info.value.message


def test_scene_error_pickles():
    err = SceneError('bad', 'bodies[0].pose', 'a.yaml')
    again = pickle.loads(pickle.dumps(err))
    assert (again.message, again.path, again.source, str(again)) == (
        'bad', 'bodies[0].pose', 'a.yaml', 'a.yaml: bodies[0].pose: bad')


# ---------------------------------------------------------------- bad input: files

FILE_ERRORS = [
    ('syntax error', 'bodies: [1, 2\nname: x\n', 'YAML syntax error at line 2, column 5', 2),
    ('tab', 'name: x\nbodies:\n\t- name: a\n', 'not tabs', 3),
    ('duplicate key', FULL.replace('    mass: 0.01\n', '    mass: 0.01\n    mass: 0.02\n'),
     "duplicate key 'mass' at line 26, column 5 (first given at line 25)", 26),
    ('two documents', 'name: a\n---\nname: b\n', 'YAML syntax error', 2),
    ('empty', '# nothing here\n', 'the file is empty', None),
    ('nan', FULL.replace('restitution: 0.0\n', 'restitution: .nan\n'), 'only finite', None),
    ('inf', FULL.replace('angle: 0.349', 'angle: -.inf'), 'only finite', None),
    ('list', '- name: a\n', 'expected the top level of the file to be a mapping', None),
    # ten levels of nine aliases: 9^10 values from 400 bytes, walked once per object
    ('alias bomb', 'a0: &a0 [x, x, x, x, x, x, x, x, x]\n' + ''.join(
        f'a{i}: &a{i} [{", ".join([f"*a{i - 1}"] * 9)}]\n' for i in range(1, 11)),
     'its YAML aliases expand to more than 1000000 values', None),
    ('alias cycle', 'name: x\nbodies: &b [*b]\n', 'contains it; write the repeated part out',
     None),
]


@pytest.mark.parametrize('text, fragment, line', [c[1:] for c in FILE_ERRORS],
                         ids=[c[0] for c in FILE_ERRORS])
def test_bad_files_are_rejected(tmp_path, text, fragment, line):
    path = write(tmp_path, text, 'bad.yaml')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    err = info.value
    assert err.source == str(path)
    assert fragment in str(err)
    assert str(err).startswith(f'{path}: ')
    if line is not None:
        assert (err.path, err.line) == ('', line)


def test_aliases_that_share_a_material_are_read(tmp_path):
    # anchors and aliases within the limits are plain YAML: a material given once
    text = FULL.replace('    mu_static: 0.5\n', '    <<: &steel {mu_static: 0.5}\n', 1)
    assert '&steel' in text
    assert load_scene(write(tmp_path, text)).bodies[0].mu_static == 0.5


def test_the_fast_parser_reads_every_shipped_scene_as_the_python_one(tmp_path):
    # libyaml reads the files; a file it refuses is read again by PyYAML for its messages
    from feeder_sim.model.scene import files as scene_files
    for name in shipped_scenes():
        text = scene_files._find(name).read_text()
        fast = yaml.load(text, Loader=scene_files._FastSceneLoader)
        assert fast == yaml.load(text, Loader=scene_files._SceneLoader), name
    assert yaml.load('x: 1e-3\ny: 1.0e3\n', Loader=scene_files._FastSceneLoader) == {
        'x': 1e-3, 'y': 1e3}


def test_nan_in_file_names_the_key(tmp_path):
    path = write(tmp_path, FULL.replace('restitution: 0.0\n', 'restitution: .NaN\n', 1))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.path == 'bodies[0].restitution'


def test_missing_file_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv('FEEDER_SIM_CONFIG', str(tmp_path))
    with pytest.raises(SceneError) as info:
        load_scene('no_such_scene')
    err = info.value
    assert err.path == '' and err.source == 'no_such_scene'
    assert 'scene not found; looked for' in err.message
    assert str(tmp_path / 'no_such_scene.yaml') in err.message
    missing = tmp_path / 'sub' / 'gone.yaml'
    with pytest.raises(SceneError, match=re.escape(str(missing))):
        load_scene(missing)


def test_directory_is_not_a_scene(tmp_path):
    with pytest.raises(SceneError, match='is a directory'):
        load_scene(tmp_path)


# ---------------------------------------------------------------- shipped scenes

def test_scene_dirs_and_shipped_scenes(tmp_path, monkeypatch):
    monkeypatch.setenv('FEEDER_SIM_CONFIG', str(tmp_path))
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    write(tmp_path, MINIMAL, 'zz_demo.yaml')
    write(tmp_path, '/**:\n  ros__parameters:\n    scene: zz_demo\n', 'zz_params.yaml')
    dirs = scene_dirs()
    assert dirs[0] == tmp_path
    assert all(d.is_dir() for d in dirs)
    repo_config = Path(feeder_sim.__file__).resolve().parents[1] / 'config'
    assert (repo_config in dirs) == repo_config.is_dir()
    names = shipped_scenes()
    assert 'zz_demo' in names and 'zz_params' not in names
    scene = load_scene('zz_demo')
    assert scene.source == str(tmp_path / 'zz_demo.yaml')
    assert scene.name == 'zz_demo'
    assert load_scene('zz_demo.yaml') == scene


def test_every_shipped_scene_loads():
    for name in shipped_scenes():
        scene = load_scene(name)
        assert isinstance(scene, Scene)
        assert all(isinstance(b, BodySpec) for b in scene.bodies)


# --- loader limits: refused at once, by size, depth and vertex count ---------------------


@pytest.mark.timeout(60)
@pytest.mark.parametrize('text, fragment', [
    ('bodies: ' + '[' * 5000 + ']' * 5000 + '\n', 'nested deeper than 32 levels'),
    ('bodies: ' + '{a: ' * 200 + '1' + '}' * 200 + '\n', 'nested deeper than 32 levels'),
    ('# padding\n' * (300_000), 'scene files are limited to 2 MiB'),
], ids=['deep lists', 'deep mappings', 'too large'])
def test_files_beyond_the_loader_limits_are_refused(tmp_path, text, fragment):
    with pytest.raises(SceneError, match=fragment):
        load_scene(write(tmp_path, text))


@pytest.mark.timeout(60)
def test_an_outline_with_too_many_vertices_is_refused_before_any_work():
    th = np.linspace(0.0, 2 * np.pi, 30_000, endpoint=False)
    data = yaml.safe_load(MINIMAL)
    data['bodies'][-1]['polygon'] = np.c_[np.cos(th), np.sin(th)].tolist()
    with pytest.raises(SceneError, match=r'30000 vertices; an outline may have at most 1000'):
        parse_scene(data)
    # the largest allowed outline is checked in about a second (O(n^2) memory: ~100 MB)
    data['bodies'][-1]['polygon'] = (0.01 * np.c_[np.cos(th[::30]), np.sin(th[::30])]).tolist()
    data['bodies'][-1]['pose'] = [0.0, 0.05, 0.0]       # clear of the floor
    assert len(parse_scene(data).bodies[-1].outlines[0]) == 1000


@pytest.mark.parametrize('pose, refused', [
    ([0.0, 0.0, 0.0], True),              # the box inside the slab (enclosed)
    ([0.0, -0.03, 0.3], True),            # deep in it, turned
    ([0.0, 0.0049, 0.0], False),          # sunk 0.1 mm of 10 mm: a contact resolves it
    ([0.0, 0.005, 0.0], False),           # resting on it
])
def test_a_part_starting_deep_inside_another_body_is_refused(pose, refused):
    data = {'bodies': [{'name': 'slab', 'type': 'static', 'pose': [0.0, 0.0, 0.0],
                        'polygon': [[-0.5, -0.1], [0.5, -0.1], [0.5, 0.0], [-0.5, 0.0]]},
                       {'name': 'box', 'type': 'dynamic', 'mass': 0.01, 'pose': pose,
                        'polygon': [[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005],
                                    [-0.01, 0.005]]}]}
    if refused:
        with pytest.raises(SceneError, match=r"bodies\[1\]\.pose: 'box' and 'slab' overlap by "
                                             r'.* m at the start .* move them apart'):
            parse_scene(data)
    else:
        parse_scene(data)


def test_the_start_overlap_uses_where_the_drive_puts_a_body_at_t_0():
    # a plate at x = 0 whose drive starts it 15 mm to the left (phase 3 pi / 2): a part at
    # x = -15 mm would start inside it, one at +15 mm is clear
    def scene(x_part):
        return {'bodies': [
            {'name': 'plate', 'type': 'kinematic', 'pose': [0.0, 0.0, 0.0],
             'polygon': [[-0.01, -0.01], [0.01, -0.01], [0.01, 0.0], [-0.01, 0.0]],
             'vibration': {'amplitude': 0.015, 'frequency': 1.0, 'angle': 0.0,
                           'phase': 3 * np.pi / 2}},
            {'name': 'box', 'type': 'dynamic', 'mass': 0.01, 'pose': [x_part, -0.005, 0.0],
             'polygon': [[-0.004, -0.004], [0.004, -0.004], [0.004, 0.004], [-0.004, 0.004]]}]}
    with pytest.raises(SceneError, match="'box' and 'plate' overlap"):
        parse_scene(scene(-0.015))
    parse_scene(scene(0.015))


# --- named parameters and expressions ------------------------------------------------------

PARAMETRIC = {
    'parameters': {'half_width': {'default': 0.01, 'unit': 'm', 'min': 0.002, 'max': 0.05},
                   'mu': 0.5, 'tilt_deg': 5},
    'bodies': [
        {'name': 'floor', 'type': 'static', 'pose': [0, 0, 0], 'mu_static': 'mu',
         'polygon': [[-1, -0.1], [1, -0.1], [1, 0], [-1, 0]]},
        {'name': 'box', 'type': 'dynamic', 'mass': 0.01, 'mu_static': 'mu',
         'polygon': [['-half_width', '-half_width / 2'], ['half_width', '-half_width / 2'],
                     ['half_width', 'half_width / 2'], ['-half_width', 'half_width / 2']],
         'pose': [0, 'half_width / 2 + 1e-3', 'radians(tilt_deg)']}]}


def test_numbers_may_be_expressions_of_named_parameters():
    scene = parse_scene(PARAMETRIC)
    assert scene.parameters == {'half_width': 0.01, 'mu': 0.5, 'tilt_deg': 5.0}
    np.testing.assert_allclose(scene.bodies[1].pose, [0.0, 0.006, math.radians(5)])
    np.testing.assert_allclose(scene.bodies[1].pieces[0][2], [0.01, 0.005])
    assert scene.bodies[0].mu_static == 0.5
    wide = parse_scene(PARAMETRIC, parameters={'half_width': 0.02, 'mu': 0.8})
    np.testing.assert_allclose(wide.bodies[1].pieces[0][2], [0.02, 0.01])
    assert wide.bodies[1].mu_static == 0.8 and wide.parameters['tilt_deg'] == 5.0
    # written back as plain numbers (and the values used), it is the same scene
    assert parse_scene(scene_to_dict(wide)) == wide


@pytest.mark.parametrize('changes, given, path, fragment', [
    ({}, {'half_width': 0.5}, 'parameters.half_width', 'outside its bounds [0.002, 0.05]'),
    ({}, {'height': 1.0}, 'parameters', 'no parameter named height; the scene declares'),
    ({'bodies[1].pose[1]': 'half_width + x'}, {}, 'bodies[1].pose[1]',
     "'x' is not defined"),
    ({'bodies[1].pose[1]': '__import__("os").getcwd()'}, {}, 'bodies[1].pose[1]',
     'cannot evaluate'),
    ({'bodies[1].pose[1]': '1 / (mu - 0.5)'}, {}, 'bodies[1].pose[1]', 'division by zero'),
    ({'bodies[1].pose[1]': '9 ** 9 ** 9'}, {}, 'bodies[1].pose[1]', 'cannot evaluate'),
    ({'bodies[1].mass': "'heavy'"}, {}, 'bodies[1].mass', "gives the text 'heavy'"),
    ({'parameters': {'sin': 1.0}}, {}, 'parameters.sin', 'taken by a function'),
    ({'parameters': {'2x': 1.0}}, {}, 'parameters.2x', 'not a name'),
    ({'bodies[1].mass': '+'.join(['0.001'] * 50_000)}, {}, 'bodies[1].mass',
     'an expression of 299999 characters'),
    ({'bodies[1].mass': '-' * 990 + '0.01'}, {}, 'bodies[1].mass', 'nested too deeply'),
    ({'bodies[1].pose[1]': '2 ** 1000000'}, {}, 'bodies[1].pose[1]',
     'beyond the largest double'),
    ({'bodies[1].pose[1]': 'True + half_width'}, {}, 'bodies[1].pose[1]',
     'True is not a number'),
    ({'bodies[1].pose[1]': '(mu > 0.1) * half_width'}, {}, 'bodies[1].pose[1]',
     'a comparison or a logical operation is not a number'),
    ({'bodies[1].pose[1]': 'half_width or 1'}, {}, 'bodies[1].pose[1]',
     'a comparison or a logical operation is not a number'),
], ids=['out of bounds', 'unknown', 'undefined name', 'no calls', 'zero division',
        'huge power', 'text result', 'function name', 'bad name', 'long', 'deep',
        'beyond double', 'boolean', 'comparison', 'logical'])
def test_parameter_and_expression_errors_name_the_key(changes, given, path, fragment):
    data = copy.deepcopy(PARAMETRIC)
    for key, value in changes.items():
        if key == 'parameters':
            data['parameters'] = value
            continue
        body, field_, index = re.match(r'bodies\[(\d)\]\.(\w+)(?:\[(\d)\])?', key).groups()
        if index is None:
            data['bodies'][int(body)][field_] = value
        else:
            data['bodies'][int(body)][field_][int(index)] = value
    with pytest.raises(SceneError) as err:
        parse_scene(data, parameters=given)
    assert err.value.path == path and fragment in err.value.message, str(err.value)


def test_each_method_takes_its_step_rule_from_the_fastest_drive():
    from feeder_sim.model.scene import METHODS, STEP_RULES
    from feeder_sim.stepping import STEPPERS
    assert set(STEP_RULES) == set(METHODS) == set(STEPPERS)
    ts, ed = STEP_RULES['time_stepping'], STEP_RULES['event_driven']
    assert ts.step([]) == 1e-3                                  # no drive: its longest step
    assert ts.step([50.0, 0.0]) == 1.0 / (400 * 50.0)           # a drive at rest sets no bound
    assert ts.step([50.0, 200.0]) == 1.0 / (400 * 200.0)        # the fastest drive does
    assert ed.step([50.0]) == 1.0 / (16 * 50.0) and ed.step([]) == math.inf
    for name, stepper in STEPPERS.items():
        assert stepper.name == name and stepper.step_rule is STEP_RULES[name]
