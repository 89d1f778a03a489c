import numpy as np
import pytest

from coupling.regions import Ball, Box, CouplingRegions, Union


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


def test_union_is_exact_outside_and_has_no_inner_face():
    """A window with a chimney: outside, the distance to the nearer box (the union's exact
    distance there); where the two boxes meet there is no face, so points there are deep
    inside; lo/hi are the bounding box."""
    wide, chimney = Box((-3.0, -4.0), (3.0, -1.0)), Box((-1.0, -4.0), (1.0, 1.0))
    u = Union((wide, chimney))
    assert u.lo == (-3.0, -4.0) and u.hi == (3.0, 1.0)
    rng = np.random.default_rng(1)
    x = rng.uniform(-5, 5, size=(4000, 2))
    d = u.signed_distance(x)
    inside = ((np.abs(x[:, 0]) < 3) & (x[:, 1] > -4) & (x[:, 1] < -1)) | (
        (np.abs(x[:, 0]) < 1) & (x[:, 1] > -4) & (x[:, 1] < 1))
    assert np.all((d < 0) == inside)
    out = ~inside
    ref = np.minimum(wide.signed_distance(x[out]), chimney.signed_distance(x[out]))
    assert np.array_equal(d[out], ref)
    # the shoulder beside the chimney is outside, 0.5 from both faces of the corner
    assert u.signed_distance(np.array([[1.5, -0.5]]))[0] == pytest.approx(0.5)
    # the junction of the two boxes (y = -1 within the chimney) is inside, not on a face
    assert u.signed_distance(np.array([[0.0, -1.0]]))[0] == pytest.approx(-1.0)
    reg = CouplingRegions(u, ghost_width=0.6)
    assert reg.particle_kinds(np.array([[0.0, 0.5], [1.5, -0.5], [2.0, 0.5]])).tolist() == [0, 1, -1]
    with pytest.raises(ValueError, match="Union.boxes"):
        Union(())
    with pytest.raises(ValueError, match="Union.boxes"):
        Union((Ball((0.0, 0.0), 1.0),))


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
