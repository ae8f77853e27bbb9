"""Where the viewer starts: input view 0's direction, moved back until the scene fills the view."""

import math

import pytest
import torch

from aesplat.view.app import framing_distance


def test_points_already_in_view_need_no_move():
    c2w = torch.eye(4, dtype=torch.float64)
    points = torch.tensor([[0.0, 0.0, 2.0], [0.5, -0.5, 2.0], [-0.9, 0.9, 3.0]], dtype=torch.float64)
    assert framing_distance(points, c2w, fov=math.radians(90), aspect=1.0) == 0.0


def test_the_distance_puts_the_kept_points_on_the_edge_of_the_view():
    # a 90-degree vertical field of view, twice as wide: a point (x, y, z) fits from t behind when
    # |x| <= (z + t) * 2 and |y| <= z + t
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])  # the camera elsewhere: points are taken in its frame
    local = torch.tensor([[0.0, 3.0, 1.0], [6.0, 0.0, 1.0]] + [[0.0, 0.0, 2.0]] * 18, dtype=torch.float64)
    world = local + c2w[:3, 3]
    t = framing_distance(world, c2w, fov=math.radians(90), aspect=2.0, keep=1.0)
    assert t == pytest.approx(2.0)  # both outliers need t = 2
    eye = c2w[:3, 3] - t * c2w[:3, 2]
    rel = world - eye
    assert (rel[:, 1].abs() <= rel[:, 2] + 1e-9).all() and (rel[:, 0].abs() <= 2 * rel[:, 2] + 1e-9).all()
    # the farthest-out 5 % are let go: here one point in twenty
    assert framing_distance(world, c2w, fov=math.radians(90), aspect=2.0, keep=0.9) < 2.0
