"""Scenes built from a few design numbers, for studies, tests and benchmarks.

Every builder returns a plain scene dict (the YAML structure), validated by ``parse_scene``,
so what a study runs can be written out as a scene file and run again from the CLI.
"""

from __future__ import annotations

import math

from feeder_sim.model.scene import parse_scene, Scene, STEP_RULES

G = 9.81


def box(half_w: float, half_h: float) -> list[list[float]]:
    """Counter-clockwise rectangle centred on the body origin."""
    return [[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]]


def ground(mu: float = 0.5, e: float = 0.0, half_length: float = 1.0,
           thickness: float = 0.1, angle: float = 0.0, name: str = 'ground') -> dict:
    """Static slab whose top face passes through the origin, tilted by ``angle`` (rad)."""
    return {'name': name, 'type': 'static',
            'polygon': [[-half_length, -thickness], [half_length, -thickness],
                        [half_length, 0.0], [-half_length, 0.0]],
            'pose': [0.0, 0.0, angle], 'mu_static': mu, 'mu_dynamic': mu, 'restitution': e}


def box_part(name: str, half_w: float, half_h: float, pose, velocity=(0.0, 0.0, 0.0),
             mu: float = 0.5, e: float = 0.0, mass: float = 0.01) -> dict:
    """A dynamic box (half sizes in m) at ``pose`` [x, y, angle] moving at ``velocity``
    [vx, vy, omega]."""
    return {'name': name, 'type': 'dynamic', 'polygon': box(half_w, half_h), 'mass': mass,
            'pose': [float(v) for v in pose], 'velocity': [float(v) for v in velocity],
            'mu_static': mu, 'mu_dynamic': mu, 'restitution': e}


def on_slope(u: float, height: float, angle: float) -> list[float]:
    """World position of the point ``u`` along and ``height`` above a slope through 0."""
    c, s = math.cos(angle), math.sin(angle)
    return [c * u - s * height, s * u + c * height]


def scene_dict(name: str, bodies: list[dict], method: str, time_step: float,
               gravity: tuple[float, float] = (0.0, -G)) -> dict:
    return {'name': name, 'gravity': list(gravity),
            'solver': {'method': method, 'time_step': time_step}, 'bodies': bodies}


def conveyor_amplitude(gamma: float, psi: float, theta: float, frequency_hz: float) -> float:
    """Drive amplitude (m, 0-peak along the drive line) giving normal acceleration gamma g_n."""
    omega = 2 * math.pi * frequency_hz
    return gamma * G * math.cos(theta) / (omega ** 2 * math.sin(psi))


def conveyor(*, psi: float, mu: float, theta: float, gamma: float, frequency_hz: float = 50.0,
             method: str = 'event_driven', time_step: float | None = None,
             tolerance: float = 1e-9, part_size: tuple[float, float] = (0.02, 0.01),
             mass: float = 0.01, track_length: float = 2.0, n_parts: int = 1,
             spacing: float | None = None, friction_impulse: bool = True,
             restitution: float = 0.0, walls: bool = False, name: str | None = None,
             mu_dynamic: float | None = None, start_with_track: bool = False) -> dict:
    """A straight track inclined at ``theta`` (rad, uphill toward +x) vibrating along a line at
    ``psi`` (rad) above the track surface, with ``n_parts`` boxes resting on it.

    ``mu`` is the static friction and, unless ``mu_dynamic`` is given, the dynamic one too.
    The parts start at rest in the world, while the track starts at its drive's largest
    speed; ``start_with_track`` starts them moving with the track instead (the point-mass
    reference's start: relative rest), which matters where nothing forgets the start (a part
    that slides back and forth without ever sticking).
    ``time_step`` defaults to the method's step rule (``STEP_RULES``: 1/400 of the vibration
    period for time stepping, 1/16 of it, the largest step, for the event-driven method).
    """
    if time_step is None:
        time_step = STEP_RULES[method].step([frequency_hz])
    w, h = part_size
    c, s = math.cos(theta), math.sin(theta)
    material = {'mu_static': mu, 'mu_dynamic': mu if mu_dynamic is None else mu_dynamic,
                'restitution': restitution}
    amplitude = conveyor_amplitude(gamma, psi, theta, frequency_hz)
    # the drive's velocity at t = 0 (phase 0: its largest), along psi above the track
    speed = amplitude * 2 * math.pi * frequency_hz if start_with_track else 0.0
    part_velocity = [speed * math.cos(theta + psi), speed * math.sin(theta + psi), 0.0]
    bodies = [{
        'name': 'track', 'type': 'kinematic',
        'polygon': [[-track_length / 2, -0.01], [track_length / 2, -0.01],
                    [track_length / 2, 0.0], [-track_length / 2, 0.0]],
        'pose': [0.0, 0.0, theta], **material,
        'vibration': {'amplitude': amplitude,
                      'frequency': frequency_hz, 'angle': psi, 'phase': 0.0},
    }]
    if walls:
        for side in (-1, 1):
            x = side * (track_length / 2 + 0.005)
            bodies.append({'name': f'wall_{"left" if side < 0 else "right"}',
                           'type': 'kinematic',
                           'polygon': box(0.005, 0.1),
                           'pose': [c * x - s * 0.09, s * x + c * 0.09, theta], **material,
                           'vibration': dict(bodies[0]['vibration'])})
    spacing = spacing if spacing is not None else 1.5 * w
    x0 = -0.5 * spacing * (n_parts - 1)
    for i in range(n_parts):
        u = x0 + i * spacing          # along the track
        bodies.append({'name': 'box' if n_parts == 1 else f'box_{i}', 'type': 'dynamic',
                       'polygon': box(w / 2, h / 2), 'mass': mass,
                       'pose': [c * u - s * h / 2, s * u + c * h / 2, theta],
                       'velocity': list(part_velocity), **material})
    return {
        'name': name or f'conveyor_psi{math.degrees(psi):.0f}_mu{mu}_theta'
                        f'{math.degrees(theta):.0f}_gamma{gamma}',
        'gravity': [0.0, -G],
        'track': 'track',
        'solver': {'method': method, 'time_step': time_step, 'tolerance': tolerance,
                   'friction_impulse': friction_impulse},
        'bodies': bodies,
    }


def build(scene: dict) -> Scene:
    return parse_scene(scene, source=f'<{scene.get("name", "scene")}>')
