import numpy as np
import pytest

from coupling.regions import Ball, Box, CouplingRegions


def test_box_signed_distance_against_brute_force():
    box = Box((0.0, 0.0), (2.0, 1.0))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 3, size=(2000, 2))
    # brute force: distance to a dense sampling of the boundary, sign from containment
    t = np.linspace(0, 1, 4001)
    edges = np.vstack(
        [np.c_[2 * t, 0 * t], np.c_[2 * t, 0 * t + 1], np.c_[0 * t, t], np.c_[0 * t + 2, t]]
    )
    dist = np.min(np.linalg.norm(x[:, None, :] - edges[None, ::4, :], axis=2), axis=1)
    inside = (x[:, 0] > 0) & (x[:, 0] < 2) & (x[:, 1] > 0) & (x[:, 1] < 1)
    ref = np.where(inside, -dist, dist)
    assert np.allclose(box.signed_distance(x), ref, atol=2e-3)


def test_ball_and_kinds():
    reg = CouplingRegions(Ball((0.0, 0.0, 0.0), 1.0), ghost_width=0.2, handshake=0.1)
    x = np.array([[0, 0, 0], [0.95, 0, 0], [1.1, 0, 0], [1.3, 0, 0]], dtype=float)
    assert reg.particle_kinds(x).tolist() == [0, 0, 1, -1]
    assert reg.prescribed_nodes(x).tolist() == [True, False, False, False]


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: Box((0, 0), (0, 1)), "Box.hi"),
        (lambda: Ball((0, 0), -1.0), "Ball.radius"),
        (lambda: CouplingRegions(Ball((0, 0), 1.0), ghost_width=0.0), "ghost_width"),
        (lambda: CouplingRegions(Ball((0, 0), 1.0), 0.1, handshake=-1), "handshake"),
    ],
)
def test_bad_input_named(make, field):
    with pytest.raises(ValueError, match=field):
        make()
