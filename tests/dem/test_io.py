"""Particle output: VTU round trip, PVD collection XML, PNG rendering, npz states."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from dem.io import ParticleWriter, load_state, read_vtu, render_png, save_state, write_vtu
from dem.packing import lattice_packing


@pytest.fixture
def frame():
    x, r = lattice_packing((0, 0, 0), (0.02, 0.02, 0.01), 0.002, "fcc")
    rng = np.random.default_rng(0)
    n = len(x)
    return dict(x=x, radius=r, velocity=rng.normal(size=(n, 3)), omega=rng.normal(size=(n, 3)),
                force=rng.normal(size=(n, 3)), kind=np.arange(n, dtype=np.int32) % 3,
                pressure=rng.random(n))


def test_vtu_round_trip(tmp_path, frame):
    write_vtu(tmp_path / "f.vtu", **frame)
    x, r, data = read_vtu(tmp_path / "f.vtu")
    np.testing.assert_array_equal(x, frame["x"])
    np.testing.assert_array_equal(r, frame["radius"])
    for k in ("velocity", "omega", "force", "kind", "pressure"):
        np.testing.assert_array_equal(data[k].reshape(frame[k].shape), frame[k])


def test_pvd_series(tmp_path, frame):
    with ParticleWriter(tmp_path / "out", "grains") as w:
        for k, t in enumerate([0.0, 1e-4, 2.5e-4]):
            w.write(t, frame["x"] + k * 1e-3, frame["radius"], velocity=frame["velocity"])
        with pytest.raises(ValueError, match="t must increase"):
            w.write(2.5e-4, frame["x"], frame["radius"])
    root = ET.parse(tmp_path / "out" / "grains.pvd").getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    sets = root.find("Collection").findall("DataSet")
    assert [float(s.get("timestep")) for s in sets] == [0.0, 1e-4, 2.5e-4]
    for k, s in enumerate(sets):
        x, _, data = read_vtu(tmp_path / "out" / s.get("file"))
        np.testing.assert_allclose(x, frame["x"] + k * 1e-3, rtol=0, atol=0)
        assert data["velocity"].shape == (len(x), 3)


def test_bad_frames(tmp_path, frame):
    with pytest.raises(ValueError, match="radius must have shape"):
        write_vtu(tmp_path / "a.vtu", frame["x"], frame["radius"][:-1])
    with pytest.raises(ValueError, match="'force' must have"):
        write_vtu(tmp_path / "a.vtu", frame["x"], frame["radius"], force=frame["force"][:3])
    with pytest.raises(ValueError, match=r"x must have shape \(n, 3\)"):
        write_vtu(tmp_path / "a.vtu", frame["x"][:, :2], frame["radius"])


@pytest.mark.parametrize("dim", [2, 3])
def test_png_not_blank(tmp_path, dim):
    import matplotlib.image

    lo, hi = ((0, 0), (0.03, 0.02)) if dim == 2 else ((0, 0, 0), (0.02, 0.02, 0.02))
    x, r = lattice_packing(lo, hi, 0.002, "hex" if dim == 2 else "fcc")
    path = render_png(tmp_path / f"p{dim}.png", x, r, scalars=x[:, 0], title=f"{dim}D")
    img = matplotlib.image.imread(path)[..., :3]
    assert img.shape[0] > 100 and img.shape[1] > 100
    # spheres cover a good part of the frame and are coloured (not only the white background)
    non_white = np.any(img < 0.95, axis=2).mean()
    assert 0.1 < non_white < 0.95 and img.std() > 0.05


def test_state_round_trip(tmp_path, frame):
    p = save_state(tmp_path / "s" / "state", t=0.125, step=17, **frame)
    st = load_state(p)
    assert st["t"] == 0.125 and st["step"] == 17
    for k, a in frame.items():
        np.testing.assert_array_equal(st[k], a)
    with pytest.raises(ValueError, match="at least one"):
        save_state(tmp_path / "e.npz")
