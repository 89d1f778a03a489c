"""The LIGGGHTS peer of the 3D calibration chamber (benchmarks/liggghts_chamber.py): the case
it writes holds our packing and valid meshes, and (if LIGGGHTS is installed) a tiny chamber
runs through consolidation and push with a finite cone force."""

import importlib.util
import math
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _module():
    spec = importlib.util.spec_from_file_location("liggghts_chamber", ROOT / "benchmarks" / "liggghts_chamber.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _parameters() -> dict:
    """A chamber of ~1300 spheres, the benchmark's case JSON form (a dict)."""
    from coupling.apps.penetration.parameters import PenetrationParameters

    prm = PenetrationParameters(dim=3, chamber_width=0.05, chamber_depth=0.01, radius=1.5e-3, cone_radius=0.003,
                                velocity=0.5, depth=0.001, vertical_stress=5e4, consolidation_tol=1e-2,
                                window_half_width=0.0065, window_depth=0.01, element_size_window=0.005,
                                element_size_far=0.01, substeps=50)
    return asdict(prm)


def _read_stl(path: Path) -> np.ndarray:
    """Triangles (m, 3, 3) of an ASCII STL, checking its structure."""
    lines = [ln.split() for ln in path.read_text().splitlines()]
    assert lines[0][0] == "solid" and lines[-1][0] == "endsolid"
    facets = [i for i, ln in enumerate(lines) if ln[0] == "facet"]
    tris = []
    for i in facets:
        normal = np.array(lines[i][2:5], float)
        assert lines[i + 1] == ["outer", "loop"] and lines[i + 5] == ["endloop"] and lines[i + 6] == ["endfacet"]
        v = np.array([lines[i + k][1:4] for k in (2, 3, 4)], float)
        n = np.cross(v[1] - v[0], v[2] - v[0])
        assert np.linalg.norm(n) > 0                       # not degenerate
        assert np.allclose(normal, n / np.linalg.norm(n), atol=1e-6)
        tris.append(v)
    return np.array(tris)


def test_write_case_holds_our_packing_and_meshes(tmp_path):
    lc = _module()
    from coupling.apps.penetration.coupled import PenetrationParameters, grain_lattice

    parameters = _parameters()
    script = lc.write_case(parameters, tmp_path)
    prm = PenetrationParameters(**parameters)
    W, H = prm.chamber_width, prm.chamber_depth
    x, radius = grain_lattice(prm, (-W / 2, -W / 2, -H), (W / 2, W / 2, 0.0), np.random.default_rng(prm.seed))

    text = (tmp_path / "grains.data").read_text().splitlines()
    assert f"{len(x)} atoms" in text
    rows = np.array([ln.split() for ln in text[text.index("Atoms") + 2:] if ln.strip()], float)
    assert len(rows) == len(x)
    np.testing.assert_allclose(rows[:, 2], 2 * radius, rtol=1e-12)   # diameters
    np.testing.assert_allclose(rows[:, 4:7], x, rtol=0, atol=1e-15)
    assert np.all(rows[:, 1] == 1) and np.all(rows[:, 3] == prm.density)

    plate = _read_stl(tmp_path / "plate.stl")
    assert plate.shape == (2, 3, 3) and np.allclose(plate[..., 2], (x[:, 2] + radius).max())
    tip, sleeve = _read_stl(tmp_path / "tip.stl"), _read_stl(tmp_path / "sleeve.stl")
    h_cone = prm.cone_radius / math.tan(math.radians(prm.apex_deg) / 2)
    assert tip[..., 2].min() == pytest.approx(0.0, abs=1e-9)          # the apex at the origin
    assert tip[..., 2].max() == pytest.approx(h_cone, rel=1e-6)
    assert sleeve[..., 2].min() == pytest.approx(h_cone, rel=1e-6)
    r = np.hypot(sleeve[..., 0], sleeve[..., 1])
    assert r.max() == pytest.approx(prm.cone_radius, rel=1e-6)

    script_text = script.read_text()
    assert "mesh/surface/stress/servo" in script_text and "fix damp all viscous" in script_text


@pytest.mark.skipif(shutil.which("liggghts") is None, reason="LIGGGHTS is not installed")
def test_tiny_chamber_runs(tmp_path):
    lc = _module()
    out = lc.run_case(_parameters(), tmp_path, cores=1, consolidation_steps=200)
    assert out["grains"] > 100 and out["consolidation_steps"] == 200
    assert out["steps"] > 0 and len(out["q_c"]) == out["steps"] // 50
    assert np.all(np.isfinite(out["q_c"])) and np.all(np.isfinite(out["tip_force"]))
    assert np.all(np.isfinite(out["f_s"]))
    assert out["depth"][-1] == pytest.approx(out["steps"] * out["dt"] * 0.5)
    assert out["push_s"] > 0 and out["setup_s"] > 0 and out["liggghts_version"].startswith("LIGGGHTS")
