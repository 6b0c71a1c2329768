"""Tests for feeder_sim.contact.collision (vertex–edge contact detection)."""

from __future__ import annotations

import math
import time

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from feeder_sim.contact.collision import (
    body_bounds,
    candidate_pairs,
    Contacts,
    evaluate_gaps,
    find_contacts,
)
from feeder_sim.model.shapes import ShapeSet

W, H = 0.02, 0.01  # box size, m
TRACK_L, TRACK_T = 0.2, 0.002  # track length and thickness, m
MARGIN = 1e-6


def box(w: float, h: float, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    return np.array([[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2],
                     [cx + w / 2, cy + h / 2], [cx - w / 2, cy + h / 2]])


def rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


class Scene:
    """Body 0 is a static track whose top edge is the world line y = 0 (unless rotated)."""

    def __init__(self, track_pieces=None, track_pos=(0.0, -TRACK_T / 2), track_angle=0.0):
        self.pieces = [track_pieces if track_pieces is not None else [box(TRACK_L, TRACK_T)]]
        self.pos = [np.array(track_pos, dtype=float)]
        self.ang = [track_angle]
        self.dyn = [False]

    def add(self, pieces, pos, angle=0.0, dynamic=True) -> int:
        self.pieces.append(pieces)
        self.pos.append(np.array(pos, dtype=float))
        self.ang.append(angle)
        self.dyn.append(dynamic)
        return len(self.pieces) - 1

    def build(self):
        return (ShapeSet.from_pieces(self.pieces), np.array(self.pos), np.array(self.ang),
                np.array(self.dyn))

    def contacts(self, margin=MARGIN, **kw) -> Contacts:
        shapes, pos, ang, dyn = self.build()
        return find_contacts(shapes, pos, ang, dyn, margin=margin, **kw)


def resting_box_scene(x=0.03, lift=0.0, angle=0.0) -> Scene:
    sc = Scene()
    sc.add([box(W, H)], (x, H / 2 + lift), angle)
    return sc


# ------------------------------------------------------------------------------------------
# ShapeSet
# ------------------------------------------------------------------------------------------


def test_from_pieces_layout():
    cw = box(W, H)[::-1]
    s = ShapeSet.from_pieces([[box(TRACK_L, TRACK_T)], [cw, box(W, H, 0.0, H)]])
    assert s.piece_start.tolist() == [0, 4, 8, 12]
    assert s.piece_body.tolist() == [0, 1, 1]
    # the clockwise piece is stored counter-clockwise
    v, vn = s.vertices[4:8], np.roll(s.vertices[4:8], -1, axis=0)
    area2 = np.sum(v[:, 0] * vn[:, 1] - v[:, 1] * vn[:, 0])
    assert area2 > 0
    np.testing.assert_allclose(s.normals[:4], [[0, -1], [1, 0], [0, 1], [-1, 0]], atol=0)
    np.testing.assert_allclose(s.radius[1], math.hypot(W / 2, H / 2))
    np.testing.assert_allclose(s.radius[2], math.hypot(W / 2, 1.5 * H))
    np.testing.assert_allclose(s.derived.piece_width, [TRACK_T, H, H])


@pytest.mark.parametrize("bad", [
    np.array([[0, 0], [2, 0], [1, 0.2], [2, 1], [0, 1]], float),  # reflex vertex
    np.array([[0, 0], [1, 0], [1, 0], [0, 1]], float),  # repeated vertex
    np.array([[0, 0], [1, 0], [2, 0]], float),  # zero area
    np.array([[0, 0], [1, 0]], float),  # too few
])
def test_from_pieces_rejects_bad_pieces(bad):
    with pytest.raises(ValueError):
        ShapeSet.from_pieces([[bad]])


def test_empty_shapes_and_contacts():
    s = ShapeSet.from_pieces([[], []])
    c = find_contacts(s, np.zeros((2, 2)), np.zeros(2), np.array([True, True]), margin=MARGIN)
    assert c.n == 0 and c.point.shape == (0, 2) and c.normal.shape == (0, 2)
    e = Contacts.empty()
    assert e.n == 0 and e.gap.shape == (0,) and e.vertex_a.dtype.kind == "i"


# ------------------------------------------------------------------------------------------
# Single box on a track
# ------------------------------------------------------------------------------------------


def test_box_resting_flat_two_corner_contacts():
    c = resting_box_scene(x=0.03).contacts()
    assert c.n == 2
    assert np.all(np.abs(c.gap) <= 1e-15)
    np.testing.assert_array_equal(c.normal, [[0.0, 1.0], [0.0, 1.0]])
    np.testing.assert_allclose(c.point, [[0.02, 0.0], [0.04, 0.0]], atol=1e-15)
    assert c.body_a.tolist() == [1, 1] and c.body_b.tolist() == [0, 0]
    assert c.vertex_a.tolist() == [4, 5]  # the box's bottom corners
    assert c.edge_b.tolist() == [2, 2]  # the track's top edge
    np.testing.assert_allclose(c.edge_param, [(0.1 - 0.02) / 0.2, (0.1 - 0.04) / 0.2])


def test_box_lifted_within_and_beyond_margin():
    c = resting_box_scene(lift=1e-7).contacts(margin=1e-6)
    assert c.n == 2
    np.testing.assert_allclose(c.gap, 1e-7, rtol=0, atol=1e-15)
    assert resting_box_scene(lift=2e-6).contacts(margin=1e-6).n == 0


def test_margin_zero_exact_touch():
    assert resting_box_scene().contacts(margin=0.0).n == 2
    assert resting_box_scene(lift=1e-12).contacts(margin=0.0).n == 0


def test_penetration_gap():
    c = resting_box_scene(lift=-1e-6).contacts()
    assert c.n == 2
    np.testing.assert_allclose(c.gap, -1e-6, rtol=0, atol=1e-15)


def test_tilted_box_on_one_corner():
    a = 0.1
    corners = box(W, H) @ rot(a).T
    sc = resting_box_scene(x=0.0, angle=a)
    sc.pos[1] = np.array([0.0, -corners[:, 1].min()])
    c = sc.contacts()
    assert c.n == 1
    # the gap is exactly the vertex's world height above the line y = 0
    assert c.gap[0] == c.point[0, 1]
    assert abs(c.gap[0]) <= 1e-15
    assert c.vertex_a[0] == 4 + int(corners[:, 1].argmin())
    np.testing.assert_array_equal(c.normal[0], [0.0, 1.0])


def test_box_on_rotated_track():
    a = math.radians(3.0)
    r = rot(a)
    sc = Scene(track_pos=(0.0, 0.0), track_angle=a)  # track top at body-frame y = T/2
    sc.add([box(W, H)], r @ np.array([0.01, TRACK_T / 2 + H / 2]), a)
    c = sc.contacts()
    assert c.n == 2
    assert np.all(np.abs(c.gap) <= 1e-15)
    np.testing.assert_allclose(c.normal, [[-math.sin(a), math.cos(a)]] * 2, rtol=0, atol=1e-15)
    assert c.vertex_a.tolist() == [4, 5]


def test_box_overhanging_track_end():
    # track occupies x in [-0.1, 0], its right end at x = 0; the box is centred at x = 0
    sc = Scene(track_pieces=[box(0.1, TRACK_T)], track_pos=(-0.05, -TRACK_T / 2))
    sc.add([box(W, H)], (0.0, H / 2))
    c = sc.contacts()
    assert c.n == 2
    assert np.all(np.abs(c.gap) <= 1e-15)
    # box's inner bottom corner on the track's top edge
    i = int(np.flatnonzero(c.body_a == 1)[0])
    assert c.vertex_a[i] == 4 and c.edge_b[i] == 2
    np.testing.assert_allclose(c.point[i], [-W / 2, 0.0], atol=1e-15)
    np.testing.assert_array_equal(c.normal[i], [0.0, 1.0])
    # the track's top corner on the box's bottom edge (normal = box bottom normal)
    j = int(np.flatnonzero(c.body_a == 0)[0])
    assert c.vertex_a[j] == 2 and c.body_b[j] == 1 and c.edge_b[j] == 4
    np.testing.assert_allclose(c.point[j], [0.0, 0.0], atol=1e-15)
    np.testing.assert_array_equal(c.normal[j], [0.0, -1.0])
    np.testing.assert_allclose(c.edge_param[j], 0.5)


def test_box_wider_than_track_uses_track_corners():
    sc = Scene(track_pieces=[box(0.01, TRACK_T)], track_pos=(0.0, -TRACK_T / 2))
    sc.add([box(W, H)], (0.0, H / 2))
    c = sc.contacts()
    assert c.n == 2
    assert c.body_a.tolist() == [0, 0] and c.vertex_a.tolist() == [2, 3]
    np.testing.assert_array_equal(c.normal, [[0.0, -1.0]] * 2)


def test_nearly_flat_box_reports_both_corners_within_margin():
    # far corner 2e-7 above the track: its adjacent edge dips by less than margin
    a = 2e-7 / W
    c = resting_box_scene(x=0.0, angle=a).contacts()
    assert c.n == 2
    assert np.all(c.gap <= MARGIN) and np.all(c.gap >= -H / 2)
    # with margin 1e-8 only the low corner is within reach
    c2 = resting_box_scene(x=0.0, angle=a).contacts(margin=1e-8)
    assert c2.n == 1


def test_depth_limits_buried_vertices():
    sc = Scene(track_pieces=[box(TRACK_L, 0.01)], track_pos=(0.0, -0.005))
    sc.add([box(W, H)], (0.0, H / 2 - 0.003))  # sunk 3 mm into a 10 mm thick track
    assert sc.contacts().n == 0  # default depth = 0.25 * 10 mm
    c = sc.contacts(depth=0.004)
    assert c.n == 2
    np.testing.assert_allclose(c.gap, -0.003, atol=1e-15)
    assert sc.contacts(depth=0.002).n == 0


def test_edge_param_unclipped_within_tolerance():
    # box lifted 1e-9 m, its corner beyond the track's end by 1e-12 m (param excess 1e-11)
    sc = Scene(track_pieces=[box(0.1, TRACK_T)], track_pos=(-0.05, -TRACK_T / 2))
    sc.add([box(W, H)], (-W / 2 + 1e-12, H / 2 + 1e-9))
    c = sc.contacts()
    # the outer box corner and the track's end corner (against the box's bottom edge) form a
    # vertex-on-vertex pair: only the contact whose edge belongs to body 0 (the track) is kept
    assert c.n == 2
    assert np.all(c.body_a == 1) and np.all(c.body_b == 0)
    assert -1e-9 < c.edge_param.min() < 0.0
    np.testing.assert_allclose(c.gap, 1e-9, atol=1e-15)
    # the same corner 1e-12 m beyond the end but resting: the end face is the least
    # penetrated face, which the box corner cannot touch, so it takes the top face it rests
    # on - the same two contacts as when lifted, now at gap 0
    sc.pos[1] = np.array([-W / 2 + 1e-12, H / 2])
    c = sc.contacts()
    assert c.n == 2
    assert np.all(c.body_a == 1) and np.all(c.body_b == 0)
    assert -1e-9 < c.edge_param.min() < 0.0
    np.testing.assert_allclose(c.gap, 0.0, atol=1e-15)


def test_flush_stacked_boxes_sunk_into_each_other_keep_their_contacts():
    # Boxes stacked flush: the upper one's bottom corners lie exactly on the lines of the
    # lower one's end faces, so once it sinks 0.1 mm into the lower box, its corners are
    # 0 from those end faces (the least penetrated) and 0.1 mm into the top face. The
    # contact is on the top face; taking none let the upper box sink through.
    sc = Scene(track_pieces=[box(0.1, TRACK_T)], track_pos=(0.0, -TRACK_T / 2))
    sc.add([box(W, H)], (0.0, H / 2))
    sc.add([box(W, H)], (0.0, 1.5 * H - 1e-4))
    c = sc.contacts()
    upper = c.body_a == 2
    assert upper.sum() == 2 and np.all(c.body_b[upper] == 1)
    np.testing.assert_allclose(c.gap[upper], -1e-4, atol=1e-12)
    np.testing.assert_allclose(c.normal[upper], [[0.0, 1.0]] * 2, atol=1e-12)


def test_static_static_and_same_body_never_tested():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2), dynamic=False)  # a static block resting on the track
    assert sc.contacts().n == 0
    sc2 = Scene()
    sc2.add([box(W, H), box(W, H, 0.0, H)], (0.0, H / 2))  # overlapping pieces, same body
    c = sc2.contacts()
    assert np.all(c.body_a != c.body_b)


def test_separate_dynamic_mask():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))
    shapes, pos, ang, dyn = sc.build()
    take = np.array([True, False])
    c = find_contacts(shapes, pos, ang, take, dynamic=dyn, margin=MARGIN)
    assert c.n == 0  # the box takes no part
    c = find_contacts(shapes, pos, ang, np.array([True, True]), dynamic=dyn, margin=MARGIN)
    assert c.n == 2


# ------------------------------------------------------------------------------------------
# Vertex-on-vertex
# ------------------------------------------------------------------------------------------


def test_vertex_on_vertex_diagonal_single_contact():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))  # body 1 on the track
    sc.add([box(W, H)], (W, 1.5 * H))  # body 2 touches body 1's top-right corner only
    c = sc.contacts()
    c12 = c.take((c.body_a + c.body_b) == 3)
    assert c12.n == 1
    # rule: the edge belongs to the lower-numbered body
    assert c12.body_b[0] == 1 and c12.body_a[0] == 2
    np.testing.assert_allclose(c12.point[0], [W / 2, H], atol=1e-15)


def test_stacked_aligned_boxes_two_contacts():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))
    sc.add([box(W, H)], (0.0, 1.5 * H))
    c = sc.contacts()
    c12 = c.take((c.body_a + c.body_b) == 3)
    assert c12.n == 2
    assert c12.body_a.tolist() == [2, 2] and c12.body_b.tolist() == [1, 1]
    np.testing.assert_array_equal(c12.normal, [[0.0, 1.0]] * 2)
    np.testing.assert_allclose(c12.point, [[-W / 2, H], [W / 2, H]], atol=1e-15)


def test_side_by_side_boxes_within_margin():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))
    sc.add([box(W, H)], (W + 5e-7, H / 2))
    c = sc.contacts()
    c12 = c.take((c.body_a + c.body_b) == 3)
    # facing sides 5e-7 apart with aligned ends: one contact per end
    assert c12.n == 2
    np.testing.assert_allclose(c12.gap, 5e-7, atol=1e-15)
    assert np.all(c12.body_b == 1)
    np.testing.assert_array_equal(c12.normal, [[1.0, 0.0]] * 2)
    assert c.take(c.body_b == 0).n == 4


# ------------------------------------------------------------------------------------------
# Compound bodies
# ------------------------------------------------------------------------------------------

MM = 1e-3


def cup_pieces():
    # U-shape 4 x 3 mm: left post, bottom (with the seam at x = 1), right post on the bottom
    off = np.array([2.0, 1.5])
    pieces = [box(1, 3, 0.5, 1.5), box(3, 1, 2.5, 0.5), box(1, 2, 3.5, 2.0)]
    return [(p - off) * MM for p in pieces]


def test_cup_on_track_contacts_only_at_outer_corners():
    sc = Scene()
    sc.add(cup_pieces(), (0.0, 1.5 * MM))
    shapes, *_ = sc.build()
    c = sc.contacts()
    assert c.n == 2
    assert c.piece_a.tolist() == [1, 2]  # the two bottom pieces (left post and bottom)
    np.testing.assert_allclose(c.point, [[-2 * MM, 0.0], [2 * MM, 0.0]], atol=1e-15)
    # choice: the seam vertex (x = -1 mm) shared by the two bottom pieces lies on a flat stretch
    # of the outer boundary, so it is not an active vertex and gives no contact at all (not
    # even a de-duplicated one)
    seam = np.flatnonzero(np.all(np.isclose(shapes.vertices, [-1 * MM, -1.5 * MM],
                                            atol=1e-15), axis=1))
    assert len(seam) == 2
    assert not shapes.derived.vertex_active[seam].any()
    assert shapes.derived.vertex_canon[seam[0]] == shapes.derived.vertex_canon[seam[1]]
    assert not np.any(np.isclose(c.point[:, 0], -1 * MM, atol=1e-12))


def test_cup_seam_on_track_seam_and_lifted():
    sc = Scene()
    sc.add(cup_pieces(), (0.0, 1.5 * MM + 3e-7))
    c = sc.contacts()
    assert c.n == 2
    np.testing.assert_allclose(c.gap, 3e-7, atol=1e-15)


def test_part_in_cup_corner():
    # small box on the cup's inner floor, pushed against the right wall
    sc = Scene()
    cup = sc.add(cup_pieces(), (0.0, 1.5 * MM))
    # inner floor at world y = 1 mm, right wall inner face at x = 1 mm
    part = sc.add([box(1 * MM, 0.5 * MM)], (0.5 * MM, 1.25 * MM))
    c = sc.contacts()
    cp = c.take((c.body_a == part) | (c.body_b == part))
    assert np.all((cp.body_a == cup) | (cp.body_b == cup))
    floor = cp.take(cp.normal[:, 1] > 0.5)
    wall = cp.take(cp.normal[:, 0] < -0.5)
    assert floor.n == 2 and wall.n == 2 and cp.n == 4
    np.testing.assert_allclose(np.sort(floor.point[:, 0]), [0.0, 1 * MM], atol=1e-15)
    assert np.all(np.abs(cp.gap) <= 1e-15)


@pytest.mark.parametrize("dx", [0.0, 1e-8, -1e-8, 3e-13])
def test_segmented_track_has_no_phantom_wall(dx):
    # two track pieces meeting at x = 0; a box corner at (or next to) the seam
    sc = Scene(track_pieces=[box(0.1, TRACK_T, -0.05, 0.0), box(0.1, TRACK_T, 0.05, 0.0)])
    sc.add([box(W, H)], (W / 2 + dx, H / 2))
    c = sc.contacts()
    assert c.n == 2
    np.testing.assert_array_equal(c.normal, [[0.0, 1.0]] * 2)
    assert np.all(np.abs(c.gap) <= 1e-15)


@pytest.mark.parametrize("dx", [0.0, 1e-8, -1e-8])
def test_track_seam_of_different_thickness_no_phantom_wall(dx):
    # same top level, the right piece is thicker
    sc = Scene(track_pieces=[box(0.1, TRACK_T, -0.05, 0.0),
                             box(0.1, 2 * TRACK_T, 0.05, -TRACK_T / 2)])
    sc.add([box(W, H)], (W / 2 + dx, H / 2))
    c = sc.contacts()
    assert c.n == 2
    np.testing.assert_array_equal(c.normal, [[0.0, 1.0]] * 2)
    # and moving along the track the box meets no wall at the seam
    sc2 = Scene(track_pieces=sc.pieces[0])
    sc2.add([box(W, H)], (-W / 2 - 5e-7, H / 2))
    c2 = sc2.contacts()
    assert c2.n == 2 and np.all(c2.normal[:, 1] == 1.0)


def test_step_in_track_is_a_real_wall():
    # right piece's top is 1 mm higher: its exposed left face is a wall
    sc = Scene(track_pieces=[box(0.1, TRACK_T, -0.05, 0.0),
                             box(0.1, TRACK_T + 0.001, 0.05, 0.0005)])
    sc.add([box(W, H)], (-W / 2 - 5e-7, H / 2))
    c = sc.contacts()
    wall = c.take(c.normal[:, 0] < -0.5)
    assert wall.n == 1  # the box's bottom-right corner against the step face
    np.testing.assert_allclose(wall.gap, 5e-7, atol=1e-15)
    assert c.take(c.normal[:, 1] > 0.5).n == 2


def test_overlapping_pieces_share_corner_once():
    # L-shape from two overlapping rectangles sharing the bottom-left corner
    pieces = [box(2 * W, H, W / 2, 0.0), box(W, 2 * H, 0.0, H / 2)]
    sc = Scene()
    sc.add(pieces, (0.0, H / 2))
    c = sc.contacts()
    assert c.n == 2
    np.testing.assert_allclose(np.sort(c.point[:, 0]), [-W / 2, 1.5 * W], atol=1e-15)


# ------------------------------------------------------------------------------------------
# evaluate_gaps
# ------------------------------------------------------------------------------------------


def two_body_state(t, p0, a0, v, w):
    return p0 + t * v, a0 + t * w


def test_evaluate_gaps_matches_find_contacts_at_moved_configuration():
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))
    sc.add([box(W, H)], (0.004, 1.5 * H))
    shapes, pos, ang, dyn = sc.build()
    c0 = find_contacts(shapes, pos, ang, dyn, margin=MARGIN)
    g0, t0 = evaluate_gaps(shapes, c0, pos, ang)
    np.testing.assert_array_equal(g0, c0.gap)
    np.testing.assert_array_equal(t0, c0.edge_param)
    pos1 = pos + np.array([[0, 0], [1e-7, 2e-7], [-3e-7, 4e-7]])
    ang1 = ang + np.array([0.0, 1e-6, -2e-6])
    c1 = find_contacts(shapes, pos1, ang1, dyn, margin=1e-5)
    g1, t1 = evaluate_gaps(shapes, c0, pos1, ang1)
    key1 = {(a, e): i for i, (a, e) in enumerate(zip(c1.vertex_a, c1.edge_b, strict=True))}
    matched = 0
    for i, (a, e) in enumerate(zip(c0.vertex_a, c0.edge_b, strict=True)):
        if (a, e) in key1:
            j = key1[(a, e)]
            assert abs(g1[i] - c1.gap[j]) <= 1e-15
            assert abs(t1[i] - c1.edge_param[j]) <= 1e-15
            matched += 1
    assert matched == c0.n == 4


def test_evaluate_gaps_is_smooth():
    # rotating box on a moving, rotating track; compare d(gap)/dt with the normal velocity
    a = 0.05
    sc = Scene(track_pos=(0.0, 0.0), track_angle=0.0)
    corners = box(W, H) @ rot(a).T
    sc.add([box(W, H)], (0.0, TRACK_T / 2 - corners[:, 1].min()), a)
    shapes, pos, ang, dyn = sc.build()
    c = find_contacts(shapes, pos, ang, dyn, margin=MARGIN)
    assert c.n == 1
    vel = np.array([[0.01, -0.02], [0.3, -0.1]])
    omega = np.array([0.7, -5.0])

    def gaps(t):
        return evaluate_gaps(shapes, c, pos + t * vel, ang + t * omega)[0]

    h = 1e-6
    fd = (gaps(h) - gaps(-h)) / (2 * h)

    def point_velocity(b, p):
        r = p - pos[b]
        return vel[b] + omega[b] * np.array([-r[1], r[0]])

    p = c.point[0]
    analytic = c.normal[0] @ (point_velocity(c.body_a[0], p) - point_velocity(c.body_b[0], p))
    assert abs(analytic) > 1e-3
    np.testing.assert_allclose(fd, analytic, rtol=1e-6)
    # edge_param also evolves smoothly (no clipping, no feature switching)
    ts = np.array([evaluate_gaps(shapes, c, pos + t * vel, ang + t * omega)[1][0]
                   for t in np.linspace(-1e-3, 1e-3, 21)])
    second = np.diff(ts, 2)
    assert np.all(np.abs(second) < 1e-6)


# ------------------------------------------------------------------------------------------
# Broad phase
# ------------------------------------------------------------------------------------------


def brute_force_pairs(lo, hi, piece_body, collides, margin, dynamic=None):
    out = []
    for i in range(len(lo)):
        for j in range(i + 1, len(lo)):
            bi, bj = piece_body[i], piece_body[j]
            if bi == bj:
                continue
            if dynamic is None:
                if not (collides[bi] or collides[bj]):
                    continue
            elif not (collides[bi] and collides[bj] and (dynamic[bi] or dynamic[bj])):
                continue
            if np.all(lo[i] <= hi[j] + margin) and np.all(lo[j] <= hi[i] + margin):
                out.append((i, j))
    return np.array(out, dtype=int).reshape(-1, 2)


@settings(max_examples=150, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 60),
       margin=st.sampled_from([0.0, 0.5, 1.0, 3.0]), stretch=st.sampled_from([0.2, 1.0, 5.0]),
       use_dynamic=st.booleans())
def test_sweep_matches_brute_force(seed, n, margin, stretch, use_dynamic):
    rng = np.random.default_rng(seed)
    # integer grid coordinates so that exactly touching boxes occur often
    lo = rng.integers(0, 40, size=(n, 2)).astype(float) * np.array([stretch, 1.0])
    hi = lo + rng.integers(0, 6, size=(n, 2))
    n_bodies = max(1, n // 2)
    piece_body = rng.integers(0, n_bodies, size=n)
    collides = rng.random(n_bodies) < 0.5
    dynamic = (rng.random(n_bodies) < 0.5) if use_dynamic else None
    got = candidate_pairs(lo, hi, piece_body, collides, margin, dynamic=dynamic)
    want = brute_force_pairs(lo, hi, piece_body, collides, margin, dynamic)
    np.testing.assert_array_equal(got, want)
    if len(got):
        assert np.all(piece_body[got[:, 0]] != piece_body[got[:, 1]])
        if dynamic is None:
            assert np.all(collides[piece_body[got]].any(axis=1))


def test_sweep_random_boxes_float():
    rng = np.random.default_rng(12345)
    for _ in range(20):
        n = 200
        lo = rng.random((n, 2)) * np.array([1.0, 0.1])
        hi = lo + rng.random((n, 2)) * 0.02
        body = np.arange(n) // 3
        collides = rng.random(body.max() + 1) < 0.7
        got = candidate_pairs(lo, hi, body, collides, 1e-3)
        want = brute_force_pairs(lo, hi, body, collides, 1e-3)
        np.testing.assert_array_equal(got, want)


def test_body_bounds_exact():
    sc = Scene()
    sc.add([box(W, H), box(W, H, W, 0.0)], (0.01, 0.02), 0.3)
    shapes, pos, ang, _ = sc.build()
    lo, hi = body_bounds(shapes, pos, ang)
    r = rot(0.3)
    for p in range(1, 3):
        wv = shapes.vertices[shapes.piece_start[p]:shapes.piece_start[p + 1]] @ r.T + pos[1]
        np.testing.assert_allclose(lo[p], wv.min(axis=0), atol=1e-17)
        np.testing.assert_allclose(hi[p], wv.max(axis=0), atol=1e-17)
    np.testing.assert_allclose(lo[0], [-TRACK_L / 2, -TRACK_T], atol=1e-17)


def test_candidate_pairs_rejects_negative_margin():
    with pytest.raises(ValueError):
        candidate_pairs(np.zeros((2, 2)), np.ones((2, 2)), np.array([0, 1]),
                        np.array([True, True]), -1.0)


# ------------------------------------------------------------------------------------------
# Ordering, determinism, scaling
# ------------------------------------------------------------------------------------------


def many_boxes_scene(n, tilt=1e-3, spacing_gap=5e-6):
    sc = Scene(track_pieces=[box(n * (W + 0.001) + 0.1, TRACK_T)])
    corners = box(W, H) @ rot(tilt).T
    # facing sides are parallel, spacing_gap apart; the AABBs overlap by ~H*tilt - spacing_gap
    pitch = (W + spacing_gap) / math.cos(tilt)
    x0 = -0.5 * pitch * (n - 1)
    for i in range(n):
        sc.add([box(W, H)], (x0 + i * pitch, -corners[:, 1].min()), tilt)
    return sc


def test_ordering_is_sorted_and_deterministic():
    sc = many_boxes_scene(30, tilt=0.0, spacing_gap=5e-7)
    c1, c2 = sc.contacts(), sc.contacts()
    for f in ("vertex_a", "edge_b", "gap", "point"):
        np.testing.assert_array_equal(getattr(c1, f), getattr(c2, f))
    key = list(zip(np.minimum(c1.body_a, c1.body_b).tolist(),
                   np.maximum(c1.body_a, c1.body_b).tolist(),
                   c1.piece_a.tolist(), c1.vertex_a.tolist(), c1.edge_b.tolist(), strict=True))
    assert key == sorted(key)
    assert len(set(zip(c1.vertex_a.tolist(), c1.edge_b.tolist(), strict=True))) == c1.n


@pytest.mark.parametrize("tilt", [0.0, 0.05])
def test_order_by_one_key_is_the_order_by_two_sorts(monkeypatch, tilt):
    # clean_contacts orders by one composite key where (bodies x vertices)^2 fits in int64,
    # else by two stable sorts; a vertex count that overflows the one key takes the other way
    from feeder_sim.contact import collision

    kernel = collision.clean_contacts
    orders = []

    def both_ways(*args):
        *head, n_vertices, n_bodies, param_tol, angle_tol = args
        one_key = kernel(*head, n_vertices, n_bodies, param_tol, angle_tol)
        two_sorts = kernel(*head, 10**6, 10**4, param_tol, angle_tol)
        orders.append((one_key.tolist(), two_sorts.tolist()))
        return one_key

    monkeypatch.setattr(collision, 'clean_contacts', both_ways)
    c = many_boxes_scene(30, tilt=tilt, spacing_gap=5e-7).contacts()
    assert len(orders) == 1 and len(orders[0][0]) == c.n > 60
    assert orders[0][0] == orders[0][1]


@pytest.mark.parametrize("n", [10, 100, 1000])
def test_scaling_many_boxes(n, capsys):
    sc = many_boxes_scene(n)
    shapes, pos, ang, dyn = sc.build()
    find_contacts(shapes, pos, ang, dyn, margin=MARGIN)  # warm-up (derived topology)
    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        c = find_contacts(shapes, pos, ang, dyn, margin=MARGIN)
    dt = (time.perf_counter() - t0) / reps
    lo, hi = body_bounds(shapes, pos, ang)
    pairs = candidate_pairs(lo, hi, shapes.piece_body, dyn, MARGIN)
    # every box rests on its low corner; neighbours' AABBs overlap but they do not touch
    assert c.n == n and np.all(c.body_b == 0) and len(pairs) > 1.5 * n
    with capsys.disabled():
        print(f"\nfind_contacts: {n} boxes, {len(pairs)} candidate pairs: {dt * 1e3:.2f} ms")


# ------------------------------------------------------------------------------------------
# Mixed shapes, supporting-vertex rule, rigid-motion invariance
# ------------------------------------------------------------------------------------------


def regular_polygon(m: int, r: float, flat_bottom: bool = True) -> np.ndarray:
    k = np.arange(m)
    phase = -math.pi / 2 - math.pi / m if flat_bottom else -math.pi / 2
    a = phase + 2 * math.pi * k / m
    return r * np.column_stack((np.cos(a), np.sin(a)))


def test_mixed_piece_sizes_on_track():
    sc = Scene()
    hexagon = regular_polygon(6, 0.005)
    tri = regular_polygon(3, 0.004, flat_bottom=False)  # resting on a vertex
    dodeca = regular_polygon(12, 0.006)
    for i, p in enumerate([hexagon, tri, dodeca, box(W, H)]):
        sc.add([p], (-0.06 + 0.035 * i, -p[:, 1].min()))
    c = sc.contacts()
    counts = np.bincount(c.body_a, minlength=5)
    assert counts.tolist() == [0, 2, 1, 2, 2]
    assert np.all(c.body_b == 0) and np.all(np.abs(c.gap) <= 1e-15)


def test_non_supporting_vertex_is_rejected():
    # box A's bottom-left corner hovers 1e-8 above B's top edge, 1e-9 inside B's right end,
    # and A's bottom edge descends to the right past B's corner: A's corner is not a
    # supporting vertex; B's corner against A's bottom edge is the contact instead
    a = -0.1
    sc = Scene()
    sc.add([box(W, H)], (0.0, H / 2))  # body 1 on the track
    corners = box(W, H) @ rot(a).T
    v_local = corners[0]  # A's bottom-left corner (world offset from A's centre)
    target = np.array([W / 2 - 1e-9, H + 1e-8])
    sc.add([box(W, H)], target - v_local, a)
    c = sc.contacts()
    c12 = c.take((c.body_a + c.body_b) == 3)
    assert c12.n == 1
    assert c12.body_a[0] == 1 and c12.body_b[0] == 2  # B's corner on A's bottom edge
    np.testing.assert_allclose(c12.normal[0], [math.sin(a), -math.cos(a)], atol=1e-15)
    assert 0 < c12.gap[0] < 1e-8


def test_rigid_motion_invariance():
    rng = np.random.default_rng(7)
    for _ in range(10):
        sc = Scene()
        xs = np.sort(rng.choice(np.arange(-4, 5), size=4, replace=False)) * 0.021
        for x in xs:
            tilt = rng.choice([0.0, rng.uniform(-0.2, 0.2)])
            corners = box(W, H) @ rot(tilt).T
            lift = rng.uniform(-5e-7, 5e-7)
            sc.add([box(W, H)], (x, -corners[:, 1].min() + lift), tilt)
        shapes, pos, ang, dyn = sc.build()
        c0 = find_contacts(shapes, pos, ang, dyn, margin=MARGIN)
        assert c0.n >= 4
        phi = rng.uniform(-math.pi, math.pi)
        shift = rng.uniform(-0.5, 0.5, size=2)
        pos1 = pos @ rot(phi).T + shift
        c1 = find_contacts(shapes, pos1, ang + phi, dyn, margin=MARGIN)
        np.testing.assert_array_equal(c1.vertex_a, c0.vertex_a)
        np.testing.assert_array_equal(c1.edge_b, c0.edge_b)
        np.testing.assert_allclose(c1.gap, c0.gap, rtol=0, atol=1e-15)
        np.testing.assert_allclose(c1.normal, c0.normal @ rot(phi).T, rtol=0, atol=1e-15)
        np.testing.assert_allclose(c1.point, c0.point @ rot(phi).T + shift, atol=1e-15)


def test_grid_compound_body_seams():
    # a 10 mm square made of 2 x 2 pieces: centre vertex inside, seam vertices flat
    q = 0.005
    grid = [box(q, q, -q / 2, -q / 2), box(q, q, q / 2, -q / 2),
            box(q, q, -q / 2, q / 2), box(q, q, q / 2, q / 2)]
    sc = Scene()
    g = sc.add(grid, (0.0, q))
    top = sc.add([box(0.004, 0.002)], (0.0005, 2 * q + 0.001 + 1e-8))  # across the top seam
    shapes, *_ = sc.build()
    assert shapes.derived.vertex_active[4:].sum() == 4 + 4  # grid's 4 outer corners + the box
    c = sc.contacts()
    on_track = c.take(c.body_b == 0)
    assert on_track.n == 2 and np.all(on_track.body_a == g)
    on_grid = c.take(c.body_a == top)
    assert on_grid.n == 2 and np.all(on_grid.body_b == g)
    np.testing.assert_array_equal(on_grid.normal, [[0.0, 1.0]] * 2)
    np.testing.assert_allclose(on_grid.gap, 1e-8, atol=1e-15)
    # slide the box so that its corner sits exactly on the seam: still no side contacts
    sc.pos[top] = np.array([0.002, 2 * q + 0.001])
    c = sc.contacts()
    on_grid = c.take(c.body_a == top)
    assert on_grid.n == 2 and np.all(on_grid.normal[:, 1] == 1.0)


def test_depth_zero_reports_only_non_penetrating():
    assert resting_box_scene(lift=-1e-9).contacts(depth=0.0).n == 0
    assert resting_box_scene(lift=0.0).contacts(depth=0.0).n == 2


def test_compiled_argsort_is_numpys_stable_argsort():
    # The kernels' hand-written sort (insertion-sorted runs, then merges that copy runs
    # already in order) gives numpy's stable permutation: ties keep their order.
    import numba

    from feeder_sim.compiled.arena import heap_arena
    from feeder_sim.contact._collision_kernels import _argsort

    @numba.njit
    def argsort(keys):
        return _argsort(heap_arena(), keys)

    rng = np.random.default_rng(3)
    for n in [0, 1, 2, 15, 16, 17, 31, 32, 33, 100, 257]:
        ints = rng.integers(0, max(1, n // 4), n)
        floats = rng.normal(size=n)
        nearly = np.sort(floats)
        nearly[rng.integers(0, max(1, n), min(n, 3))] += 0.1
        for keys in (ints, floats, np.sort(floats), np.sort(floats)[::-1].copy(), nearly):
            np.testing.assert_array_equal(argsort(keys), np.argsort(keys, kind='stable'))


def test_the_integer_keys_radix_sort_is_numpys_stable_argsort():
    # _argsort_int (least-significant-digit radix from 100 keys on, the comparison sort below
    # that or for negative keys) gives numpy's stable permutation, from a heap state and from
    # an arena too small for it: ties (many, in narrow ranges), keys of 1 to 62 bits, a
    # digit every key shares (its pass skipped), sorted and reversed input, one negative key.
    import numba

    from feeder_sim.compiled.arena import borrow, heap_arena, new_arena, release
    from feeder_sim.contact._collision_kernels import _argsort_int

    @numba.njit
    def on_heap(keys):
        return _argsort_int(heap_arena(), keys)

    @numba.njit
    def in_arena(state, keys):
        ar = borrow(state)
        out = _argsort_int(ar, keys).copy()
        release(ar, 0)
        return out

    arena = new_arena(256)
    rng = np.random.default_rng(5)
    for n in [0, 1, 99, 100, 101, 1000, 5000]:
        cases = [rng.integers(0, max(1, n // 8), n), rng.integers(0, 2, n),
                 rng.integers(0, 1 << 40, n), rng.integers(0, 1 << 62, n),
                 (rng.integers(0, 50, n) << 16) | 0xAB, np.full(n, 7),
                 np.arange(n), np.arange(n)[::-1].copy()]
        if n:
            negative = rng.integers(0, 1000, n)
            negative[n // 2] = -3
            cases.append(negative)
        for keys in cases:
            keys = keys.astype(np.int64)
            want = np.argsort(keys, kind='stable')
            np.testing.assert_array_equal(on_heap(keys), want)
            np.testing.assert_array_equal(in_arena(arena.state, keys), want)
