"""Scene files: YAML -> validated, frozen dataclasses.

A scene describes one world (see docs/interfaces.md §1). Everything is checked before anything
runs; the first problem raises :class:`SceneError`, whose message names the file, the key path
(``bodies[2].polygon``) and what is expected. Units are SI (m, s, kg, rad) throughout.

* :mod:`.specs`: the dataclasses (:class:`Scene`, :class:`BodySpec`, ...) and the limits.
* :mod:`.errors`: :class:`SceneError`, and the checkers' ``_Invalid`` it is made from.
* :mod:`.expressions`: numbers written as expressions of the scene's ``parameters``.
* :mod:`.fields`: the checker of each kind of value (number, list, text, choice, mapping).
* :mod:`.outlines`: polygons checked and decomposed into convex pieces.
* :mod:`.parse`: :func:`parse_scene` block by block, placement checks, :func:`scene_to_dict`.
* :mod:`.files`: finding and reading scene files (hardened YAML), :func:`load_scene`.

Each imports only those above it in: errors, specs <- expressions <- fields <- outlines <-
parse <- files.
"""

from feeder_sim.model.scene.errors import SceneError
from feeder_sim.model.scene.files import (
    load_scene,
    read_scene_data,
    read_yaml,
    scene_dirs,
    shipped_scenes,
)
from feeder_sim.model.scene.parse import (
    check_placement,
    overlap_problem,
    override_solver,
    parse_scene,
    scene_to_dict,
)
from feeder_sim.model.scene.specs import (
    BODY_TYPES,
    BodySpec,
    MAX_ANGLE_RAD,
    MAX_FILE_BYTES,
    MAX_LENGTH_M,
    MAX_NESTING,
    MAX_POLYGON_VERTICES,
    MAX_SPEED_MPS,
    MAX_SPIN_RAD_S,
    METHODS,
    MIN_PIECE_WIDTH_M,
    MIN_TIME_STEP_S,
    OutcomeSpec,
    Scene,
    SensorSpec,
    SinkSpec,
    SolverSpec,
    SourceSpec,
    STEP_RULES,
    StepRule,
    Vibration,
    within_bounds,
)

__all__ = [
    'BODY_TYPES', 'BodySpec', 'check_placement', 'load_scene', 'MAX_ANGLE_RAD', 'MAX_FILE_BYTES',
    'MAX_LENGTH_M', 'MAX_NESTING', 'MAX_POLYGON_VERTICES', 'MAX_SPEED_MPS', 'MAX_SPIN_RAD_S',
    'METHODS', 'MIN_PIECE_WIDTH_M', 'MIN_TIME_STEP_S', 'OutcomeSpec', 'overlap_problem',
    'override_solver', 'parse_scene', 'read_scene_data', 'read_yaml', 'Scene', 'scene_dirs',
    'scene_to_dict', 'SceneError', 'SensorSpec', 'shipped_scenes', 'SinkSpec', 'SolverSpec',
    'SourceSpec', 'STEP_RULES', 'StepRule', 'Vibration', 'within_bounds',
]
