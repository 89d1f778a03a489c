"""Cone readings as ISO 22476-1 defines them: q_c on the tip area, f_s on a fixed sleeve area."""

import numpy as np
import pytest

from coupling.apps.penetration.parameters import PenetrationParameters
from coupling.apps.penetration.penetrators import (
    SLEEVE_OVER_DIAMETER,
    cone_clump,
    cone_parts,
    cone_record,
    filtered,
    penetrator_clump,
    tip_height,
)


@pytest.mark.parametrize("dim", [2, 3])
def test_sleeve_is_the_shaft_just_above_the_cone(dim):
    prm = PenetrationParameters(dim=dim, window_half_width=0.04, chamber_width=0.4)
    R = prm.cone_radius
    if dim == 2:
        pen, _, tip = cone_clump(R, prm.apex_deg, 10 * R, prm.radius)
    else:
        pen, _, tip = penetrator_clump(prm, 10 * R)
    pen = pen + np.array([0.01, -0.2, 0.05])                     # any rigid placement
    parts = cone_parts(pen, tip, prm)
    ax = dim - 1
    z = pen[:, ax] - pen[:, ax].min()
    base = z[parts.tip].max()
    # the cone's base, measured from the lowest centre (inset from the apex by about a grain radius)
    assert base == pytest.approx(tip_height(prm), abs=2 * prm.radius)
    assert parts.sleeve.any() and not (parts.sleeve & parts.tip).any()
    assert base < z[parts.sleeve].min() < base + prm.radius
    top = base + SLEEVE_OVER_DIAMETER * 2 * R
    assert z[parts.sleeve].max() <= top and z[parts.sleeve].max() > top - prm.radius
    assert (z[~parts.tip & ~parts.sleeve] > top).all()        # the shaft above the sleeve is not counted


def test_readings_divide_by_the_fixed_areas():
    """A unit vertical force on every sphere: q_c and f_s are the counts over the ISO areas,
    the same at any depth (a partly embedded sleeve is still divided by its whole area)."""
    prm = PenetrationParameters()
    R = prm.cone_radius
    pen, _, tip = cone_clump(R, prm.apex_deg, 10 * R, prm.radius)
    parts = cone_parts(pen, tip, prm)
    force = np.zeros((len(pen), 3))
    force[:, 1] = 1.0
    for depth in (0.001, 0.03):
        h = cone_record(prm, force, parts, depth, 1, 0.0)
        assert h["q_c"] == pytest.approx(tip.sum() / (2 * R))
        assert h["f_s"] == pytest.approx(parts.sleeve.sum() / (2 * SLEEVE_OVER_DIAMETER * 2 * R))
        assert h["friction_ratio"] == pytest.approx(h["f_s"] / h["q_c"])
        assert h["shaft_force"] == pytest.approx((~tip).sum())


def test_filtered_is_a_centred_moving_average():
    depth = np.linspace(0, 0.1, 101)
    rows = [{"depth": d, "q_c": 1.0 + (k % 2)} for k, d in enumerate(depth)]   # 1, 2, 1, 2, ...
    smooth = filtered(rows, "q_c", 0.02 + 1e-9)                                # 21 rows each
    assert np.allclose(smooth[15:-15], 1.5, atol=1 / 21 + 1e-12)
    ramp = [{"depth": d, "q_c": d} for d in depth]
    assert np.allclose(filtered(ramp, "q_c", 0.02 + 1e-9)[10:-10], depth[10:-10])   # linear: unchanged
