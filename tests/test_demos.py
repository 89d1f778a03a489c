"""Every demo runs briefly (GRANFE_SHORT=1), serially and under mpiexec -n 2, and passes its
own closing assertions; results.json must be written."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = Path(sys.executable).parent / "mpiexec"

# (script, runs under MPI)
DEMOS = [
    ("demos/2d/plate_hole.py", True),
    ("demos/2d/strip_footing.py", True),
    ("demos/2d/biaxial_shear_band.py", True),
    ("demos/2d/terzaghi.py", True),
    ("demos/2d/mandel.py", True),
    ("demos/2d/micromorphic_shear_layer.py", True),
    ("demos/2d/grain_consolidation.py", False),
    ("demos/2d/cptu_coupled.py", False),
    ("demos/2d/fe2_biaxial.py", True),
    ("demos/2d/coupled_punch.py", True),
    ("demos/2d/wave_through_overlap.py", True),
    ("demos/2d/cpt_coupled.py", True),
    ("demos/2d/cpt_moving_window.py", False),
    ("demos/3d/pile_penetration_stress.py", False),
    ("demos/3d/cavity_expansion_stress.py", False),
    ("demos/3d/micromorphic_uniaxial.py", False),
    ("demos/3d/micromorphic_plastic_triaxial.py", True),
    ("demos/3d/micromorphic_finite_plastic_compression.py", True),
    ("demos/3d/sheared_till.py", False),
    ("demos/3d/cptu_coupled.py", False),
    ("demos/3d/seed004_stress_paths.py", False),
    ("demos/3d/fe2_triaxial.py", True),
]
DEMOS += [(str(p.relative_to(ROOT)), True) for p in sorted((ROOT / "demos" / "1d").glob("*.py"))]


def _run(cmd, out):
    env = dict(os.environ, GRANFE_SHORT="1", PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg",
               NUMBA_NUM_THREADS="1")
    proc = subprocess.run(cmd + ["--out", str(out)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    results = json.loads((out / "results.json").read_text())
    assert results, "empty results.json"
    return results


@pytest.mark.slow
@pytest.mark.parametrize("script", [d for d, _ in DEMOS])
def test_demo_serial(script, tmp_path):
    _run([sys.executable, script], tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("script", [d for d, mpi in DEMOS if mpi])
def test_demo_two_ranks(script, tmp_path):
    if not MPIEXEC.exists():
        pytest.skip("mpiexec not in the virtual environment")
    _run([str(MPIEXEC), "-n", "2", sys.executable, script], tmp_path)


# benchmarks, reduced (GRANFE_SHORT=1): they run and their own checks pass
BENCHMARKS = [
    ["benchmarks/stability.py"],
    ["benchmarks/cpt_vs_full_dem.py", "--parts", "2d"],
]


@pytest.mark.slow
@pytest.mark.parametrize("cmd", BENCHMARKS, ids=lambda c: c[0])
def test_benchmark_short(cmd, tmp_path):
    results = _run([sys.executable, *cmd], tmp_path)
    if "stability" in cmd[0]:
        assert {r["status"] for r in results["runs"]} <= {"finished", "stopped", "refused"}
    else:
        assert all(np.isfinite(p["q_c_rms_error"]) for p in results["coupled"])
