"""The simulated world: bodies as arrays (struct of arrays) and the state that evolves.

A :class:`World` is built from a :class:`~feeder_sim.model.scene.Scene` and does not change
while the simulation runs (except the vibration drives, which take commands); a part added or
taken away makes a new World from the old one (:meth:`World.with_part`,
:meth:`World.without_body`). A :class:`State`
holds what the stepping methods change: time, centre-of-mass positions, angles and velocities of
every body. Static and kinematic bodies have rows in the state too; their rows are written from the
prescribed motion, never integrated.

Poses in the state are those of each body's centre of mass; scene files and published poses use
the body frame of the scene file, related by ``origin = com - R(angle) @ com_local``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
import math
from typing import NamedTuple

import numpy as np

from feeder_sim.model.geometry import mass_properties
from feeder_sim.model.scene import BODY_TYPES as scene_body_types
from feeder_sim.model.scene import BodySpec, Scene
from feeder_sim.model.shapes import ShapeSet
from feeder_sim.model.vibration import Drive, drive_table, DriveSegments

# body kinds, as codes in World.body_type (the names and their order are scene.BODY_TYPES')
BODY_TYPES = {name: code for code, name in enumerate(scene_body_types)}
STATIC, KINEMATIC, DYNAMIC = (BODY_TYPES[k] for k in ('static', 'kinematic', 'dynamic'))
# how a compiled stepper moves a body: FIXED (static, or kinematic at rest), DRIVEN (a drive's
# sinusoid) or MOVING (dynamic: by the equations of motion)
FIXED, DRIVEN, MOVING = 0, 1, 2


def rot(theta: np.ndarray | float) -> np.ndarray:
    """Rotation matrices for angles (rad): shape (2, 2) or (n, 2, 2)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of a x b for stacks of 2-vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def perp(v: np.ndarray) -> np.ndarray:
    """v rotated by +90 degrees; also omega x v for unit omega about z."""
    return np.stack([-v[..., 1], v[..., 0]], -1)


@dataclass
class State:
    """Everything that changes in time. Units: s, m, rad, m/s, rad/s."""

    t: float
    position: np.ndarray   # (n, 2) centre of mass, world frame
    angle: np.ndarray      # (n,)
    velocity: np.ndarray   # (n, 2)
    omega: np.ndarray      # (n,)

    def copy(self) -> State:
        return State(self.t, self.position.copy(), self.angle.copy(), self.velocity.copy(),
                     self.omega.copy())


class _BodyModel(NamedTuple):
    mass: float             # kg; inf for static and kinematic bodies
    inertia: float          # kg m^2 about the centre of mass; inf likewise
    com_local: np.ndarray   # (2,) centre of mass in the scene-file body frame
    pieces: list            # convex pieces about the centre of mass
    drive: Drive | None


def _body_model(body: BodySpec) -> _BodyModel:
    """What a world keeps of one body of a scene."""
    dynamic = body.type == 'dynamic'
    props = mass_properties(body.pieces, mass=body.mass, density=body.density) if dynamic \
        else mass_properties(body.pieces, density=1.0)
    drive = None
    if body.vibration is not None:
        theta = body.pose[2] + body.vibration.angle
        drive = Drive(np.array([math.cos(theta), math.sin(theta)]), body.vibration.amplitude,
                      body.vibration.frequency, body.vibration.phase)
    return _BodyModel(props.mass if dynamic else math.inf,
                      props.inertia if dynamic else math.inf, np.asarray(props.centroid, float),
                      [np.asarray(p, float) - props.centroid for p in body.pieces], drive)


def _centre_of_mass(pose: np.ndarray, com_local: np.ndarray) -> np.ndarray:
    return pose[:2] + rot(pose[2]) @ com_local


def mix(a: np.ndarray, b: np.ndarray, rule: str) -> np.ndarray:
    """Material value of a contact from the values of its two bodies.

    Friction uses the geometric mean (a frictionless coating makes the pair frictionless, as in
    Box2D); restitution the larger value. Equal inputs give exactly that value.
    """
    if rule == 'friction':
        out = np.sqrt(a * b)
    else:
        out = np.maximum(a, b)
    return np.where(a == b, a, out)


@dataclass
class World:
    """Bodies of one scene, as arrays indexed by body number (scene-file order)."""

    scene: Scene
    names: tuple[str, ...]
    body_type: np.ndarray      # (n,) STATIC / KINEMATIC / DYNAMIC
    mass: np.ndarray           # (n,) kg; inf for static and kinematic bodies
    inertia: np.ndarray        # (n,) kg m^2 about the centre of mass
    inv_mass: np.ndarray       # (n,) 1/kg; 0 for non-dynamic bodies
    inv_inertia: np.ndarray    # (n,)
    com_local: np.ndarray      # (n, 2) centre of mass in the scene-file body frame
    shapes: ShapeSet
    mu_static: np.ndarray
    mu_dynamic: np.ndarray
    restitution: np.ndarray
    gravity: np.ndarray        # (2,) m/s^2
    base_position: np.ndarray  # (n, 2) centre of mass at zero drive displacement
    base_angle: np.ndarray     # (n,)
    drives: tuple[Drive | None, ...]
    track_index: int | None    # body whose x axis is "along the track" in reports
    # the last drive table and the segments it was built from: a compiled stepper asks for it
    # at every call, and segments only change at a command
    _drive_memo: tuple[tuple, DriveSegments] | None = field(
        default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_scene(cls, scene: Scene) -> World:
        n = len(scene.bodies)
        models = [_body_model(body) for body in scene.bodies]
        pose = np.array([b.pose for b in scene.bodies], dtype=float).reshape(n, 3)
        com_local = np.array([m.com_local for m in models], dtype=float).reshape(n, 2)
        body_type = np.array([BODY_TYPES[b.type] for b in scene.bodies], dtype=np.int8)
        mass = np.array([m.mass for m in models], dtype=float)
        inertia = np.array([m.inertia for m in models], dtype=float)
        dynamic = body_type == DYNAMIC
        track_index = scene.bodies.index(
            next(b for b in scene.bodies if b.name == scene.track)) if scene.track else None
        return cls(
            scene=scene,
            names=tuple(b.name for b in scene.bodies),
            body_type=body_type,
            mass=mass,
            inertia=inertia,
            inv_mass=np.where(dynamic, 1.0 / mass, 0.0),
            inv_inertia=np.where(dynamic, 1.0 / inertia, 0.0),
            com_local=com_local,
            shapes=ShapeSet.from_pieces([m.pieces for m in models]),
            mu_static=np.array([b.mu_static for b in scene.bodies], float),
            mu_dynamic=np.array([b.mu_dynamic for b in scene.bodies], float),
            restitution=np.array([b.restitution for b in scene.bodies], float),
            gravity=np.asarray(scene.gravity, float),
            base_position=pose[:, :2] + np.einsum('nij,nj->ni', rot(pose[:, 2]), com_local),
            base_angle=pose[:, 2].copy(),
            drives=tuple(m.drive for m in models),
            track_index=track_index,
        )

    def with_part(self, body: BodySpec) -> World:
        """This world and the dynamic body ``body`` as its last one, at ``body.pose``.

        A part added while the world runs: only ``body`` is looked at (its mass properties
        and pieces), the other bodies' arrays are copied, and nothing accepted before is
        checked again."""
        m = _body_model(body)
        pose = np.asarray(body.pose, float)
        base = _centre_of_mass(pose, m.com_local)
        return replace(
            self,
            scene=replace(self.scene, bodies=(*self.scene.bodies, body)),
            names=(*self.names, body.name),
            body_type=np.append(self.body_type, np.int8(DYNAMIC)),
            mass=np.append(self.mass, m.mass),
            inertia=np.append(self.inertia, m.inertia),
            inv_mass=np.append(self.inv_mass, 1.0 / m.mass),
            inv_inertia=np.append(self.inv_inertia, 1.0 / m.inertia),
            com_local=np.vstack((self.com_local, m.com_local)),
            shapes=self.shapes.with_body(self.n, m.pieces),
            mu_static=np.append(self.mu_static, body.mu_static),
            mu_dynamic=np.append(self.mu_dynamic, body.mu_dynamic),
            restitution=np.append(self.restitution, body.restitution),
            base_position=np.vstack((self.base_position, base)),
            base_angle=np.append(self.base_angle, pose[2]),
            drives=(*self.drives, None),
        )

    def without_body(self, index: int) -> World:
        """This world without body ``index`` (a part taken away); the bodies after it move
        down by one index, drives and their commands go on."""
        keep = np.arange(self.n) != index
        track = self.track_index
        return replace(
            self,
            scene=replace(self.scene, bodies=tuple(
                b for k, b in enumerate(self.scene.bodies) if k != index)),
            names=tuple(name for k, name in enumerate(self.names) if k != index),
            body_type=self.body_type[keep], mass=self.mass[keep], inertia=self.inertia[keep],
            inv_mass=self.inv_mass[keep], inv_inertia=self.inv_inertia[keep],
            com_local=self.com_local[keep], shapes=self.shapes.without_body(index),
            mu_static=self.mu_static[keep], mu_dynamic=self.mu_dynamic[keep],
            restitution=self.restitution[keep], base_position=self.base_position[keep],
            base_angle=self.base_angle[keep],
            drives=tuple(d for k, d in enumerate(self.drives) if k != index),
            track_index=track if track is None or track < index else
            (None if track == index else track - 1),
        )

    def centre_of_mass(self, body: int, pose: np.ndarray) -> np.ndarray:
        """(2,) centre of mass (m, world frame) of ``body`` with its scene-file frame at
        ``pose`` [x, y, angle]."""
        return _centre_of_mass(np.asarray(pose, float), self.com_local[body])

    def piece_outlines(self, state: State, body: int) -> list[np.ndarray]:
        """The convex pieces of ``body`` in the world frame at ``state`` (m)."""
        shapes = self.shapes
        r = rot(state.angle[body])
        return [shapes.vertices[shapes.piece_start[p]:shapes.piece_start[p + 1]] @ r.T
                + state.position[body] for p in np.flatnonzero(shapes.piece_body == body)]

    @property
    def n(self) -> int:
        return len(self.names)

    @cached_property
    def name_index(self) -> dict[str, int]:
        """Body name -> index."""
        return {name: i for i, name in enumerate(self.names)}

    # Derived once: the stepping methods read these on every step.
    @cached_property
    def dynamic(self) -> np.ndarray:
        return self.body_type == DYNAMIC

    @cached_property
    def driven(self) -> np.ndarray:
        """Indices of bodies that have a vibration drive."""
        return np.array([i for i, d in enumerate(self.drives) if d is not None], dtype=int)

    @cached_property
    def _driven_drives(self) -> list[Drive]:
        return [self.drives[i] for i in self.driven.tolist()]

    def drive_segments(self, t: float) -> DriveSegments:
        """The drive table from time ``t`` (s) on, one row per body of :attr:`driven`."""
        drives = self._driven_drives
        segs = tuple([drive.segment(t) for drive in drives])
        memo = self._drive_memo
        # (tuples compare their items by identity first: the same segments are equal at once)
        if memo is None or memo[0] != segs:
            memo = self._drive_memo = (segs, drive_table(drives, segs,
                                                         self.base_position[self.driven]))
        return memo[1]

    @cached_property
    def radius(self) -> np.ndarray:
        """(n,) largest distance of a body's vertices from its centre of mass, m."""
        radius = np.zeros(self.n)
        np.maximum.at(radius, self.shapes.piece_body, self.shapes.radius)
        return radius

    @cached_property
    def pair_materials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, n) tables of mu_static, mu_dynamic and restitution of a contact between bodies
        i and j (``mix`` of the two bodies' values)."""
        pair = np.indices((self.n, self.n)).reshape(2, -1)
        return tuple(
            mix(values[pair[0]], values[pair[1]], rule).reshape(self.n, self.n)
            for values, rule in ((self.mu_static, 'friction'), (self.mu_dynamic, 'friction'),
                                 (self.restitution, 'restitution')))

    def initial_state(self) -> State:
        velocity = np.array([b.velocity for b in self.scene.bodies], float).reshape(self.n, 3)
        state = State(0.0, self.base_position.copy(), self.base_angle.copy(),
                      np.where(self.dynamic[:, None], velocity[:, :2], 0.0),
                      np.where(self.dynamic, velocity[:, 2], 0.0))
        self.apply_prescribed_motion(state)
        return state

    def prescribed_acceleration(self, t: float) -> np.ndarray:
        """(n, 2) acceleration of driven bodies at time t (zero elsewhere)."""
        acc = np.zeros((self.n, 2))
        for i in self.driven:
            _, _, a = self.drives[i].motion(t)
            acc[i] = a * self.drives[i].direction
        return acc

    def apply_prescribed_motion(self, state: State) -> None:
        """Write the positions and velocities of driven bodies at ``state.t`` into ``state``."""
        for i in self.driven:
            d, v, _ = self.drives[i].motion(state.t)
            u = self.drives[i].direction
            state.position[i] = self.base_position[i] + d * u
            state.velocity[i] = v * u

    def body_frame_pose(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        """Scene-file body frame origins (n, 2) and angles (n,) for a state."""
        origin = state.position - np.einsum('nij,nj->ni', rot(state.angle), self.com_local)
        return origin, state.angle.copy()

    @property
    def track_angle(self) -> float:
        """Angle of the track body's x axis at rest (rad, world frame); 0 without a track:
        the reference of a part's orientation."""
        return 0.0 if self.track_index is None else float(self.base_angle[self.track_index])

    def track_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """Origin and unit x axis of the track body at rest (world frame)."""
        origin = np.zeros(2) if self.track_index is None else self.base_position[self.track_index]
        theta = self.track_angle
        return origin, np.array([math.cos(theta), math.sin(theta)])

    def kinetic_energy(self, state: State) -> float:
        """J, dynamic bodies only."""
        dyn = self.dynamic
        return float(0.5 * np.sum(self.mass[dyn] * np.sum(state.velocity[dyn] ** 2, axis=1))
                     + 0.5 * np.sum(self.inertia[dyn] * state.omega[dyn] ** 2))

    def potential_energy(self, state: State) -> float:
        """J, gravity on dynamic bodies, zero at the world origin."""
        dyn = self.dynamic
        return float(-np.sum(self.mass[dyn] * (state.position[dyn] @ self.gravity)))
