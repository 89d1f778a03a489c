"""The continuum-model seam: the registry, a model with quadrature-point history (trial /
commit / restore, checkpoints, MPI), and the problem's API over any model."""

import subprocess
import sys

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

from granfe.dynamics import GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.models import MODELS, Micropolar, StrainMemory, model_class
from granfe.models.strain_memory import StrainMemoryMaterial
from granfe.problem import ContinuumProblem, MicropolarProblem
from granfe.solvers import SolveDidNotConverge

LAM, MU, S = 2.0e6, 1.0e6, 20.0
H = 1.0


def test_registry_names_every_model():
    assert MODELS["micropolar"] is Micropolar and MODELS["strain_memory"] is StrainMemory
    with pytest.raises(ValueError, match="unknown continuum model 'plastic'"):
        model_class("plastic")


def _bar(comm=MPI.COMM_WORLD, n=4, **kwargs):
    """Unit square in plane strain: u_x = 0 on the left, u_y = 0 at the bottom, u_x = d on
    the right, the top free: a homogeneous uniaxial stress state."""
    domain = mesh.create_unit_square(comm, n, n)
    p = ContinuumProblem(domain, StrainMemory(StrainMemoryMaterial(LAM, MU, softening=S)),
                         prefix=f"sm{id(domain)}_", **kwargs)
    p.fix(lambda x: np.isclose(x[0], 0.0), "u_x")
    p.fix(lambda x: np.isclose(x[1], 0.0), "u_y")
    d = p.fix(lambda x: np.isclose(x[0], 1.0), "u_x", 0.0)
    return p, d


def _closed_form(e, k_before):
    """Reaction on the right [N/m] of the uniaxial bar at strain e after a largest strain
    k_before, and the largest strain after."""
    e_yy = -LAM / (LAM + 2 * MU) * e
    k = max(k_before, np.hypot(e, e_yy))
    modulus = 4 * MU * (LAM + MU) / (LAM + 2 * MU)
    return modulus * e / (1 + S * k) * H, k


def _right(x):
    return np.isclose(x[0], 1.0)


def test_history_is_kept_between_load_steps():
    p, d = _bar()
    assert p.state and set(p.state.committed) == {"max_strain"}
    k = 0.0
    for e in (0.01, 0.005, 0.0, 0.02, 0.01):     # load, unload, reload beyond, unload
        d.value = e
        p.solve()
        expected, k = _closed_form(e, k)
        assert p.reaction(_right, "u_x") == pytest.approx(expected, rel=1e-9, abs=1e-6)
        qp = p.state.committed["max_strain"].x.array
        assert np.allclose(qp, k, rtol=1e-12)
    # without memory the unloaded bar would follow the tangent of the current strain
    memoryless, _ = _closed_form(0.01, 0.0)
    assert p.reaction(_right, "u_x") < 0.9 * memoryless


def test_failed_solve_restores_fields_and_state():
    p, d = _bar()
    p.fix(lambda x: np.isclose(x[0], 0.0), "u_y")   # clamped: not homogeneous, Newton iterates
    d.value = 0.01
    p.solve()
    w, state = p.w.x.array.copy(), p.state.committed["max_strain"].x.array.copy()
    p.petsc_options["snes_max_it"] = 1
    p.invalidate()
    d.value = 0.03
    with pytest.raises(SolveDidNotConverge, match="DIVERGED_MAX_IT"):
        p.solve()
    assert np.array_equal(p.w.x.array, w)
    assert np.array_equal(p.state.committed["max_strain"].x.array, state)
    assert np.array_equal(p.state.trial["max_strain"].x.array, state)


def test_state_survives_a_checkpoint(tmp_path):
    p, d = _bar()
    d.value = 0.02
    p.solve()
    p.write_checkpoint(tmp_path)
    q, d2 = _bar()
    q.read_checkpoint(tmp_path)
    assert np.array_equal(q.state.committed["max_strain"].x.array,
                          p.state.committed["max_strain"].x.array)
    d2.value = 0.01                              # unloading remembers the 2 % strain
    q.solve()
    _, k = _closed_form(0.02, 0.0)
    expected, _ = _closed_form(0.01, k)
    assert q.reaction(_right, "u_x") == pytest.approx(expected, rel=1e-9)


@pytest.mark.mpi
def test_history_on_any_rank_count():
    """The closed form holds on every rank count; the ghost cells' history equals their
    owners' (a rank integrating stale ghost values would miss it)."""
    p, d = _bar(n=6)
    k = 0.0
    for e in (0.015, 0.004):
        d.value = e
        p.solve()
        expected, k = _closed_form(e, k)
        assert p.reaction(_right, "u_x") == pytest.approx(expected, rel=1e-9)
    assert np.allclose(p.state.committed["max_strain"].x.array, k, rtol=1e-12)


def test_dynamic_steps_commit_the_state():
    p, d = _bar()
    stepper = GeneralizedAlpha(p, dt=1e-4, rho_inf=0.5)
    assert stepper._affine is None                # nonlinear: SNES every step
    d.value = 0.01
    stepper.step()
    k = p.state.committed["max_strain"].x.array
    assert k.max() > 0 and np.array_equal(k, p.state.trial["max_strain"].x.array)


def test_elastic_model_has_no_state():
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 2, 2)
    p = MicropolarProblem(domain, MicropolarMaterial(lam=1.0, mu=1.0, kappa=0.5))
    assert not p.state and p.dx.metadata() == {}


# ---- the problem's API over any model ---------------------------------------------------

def _block(**material):
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0.0, 0.0], [2.0, H]], [8, 4])
    mat = MicropolarMaterial(**{"lam": 1e6, "mu": 1e6, "kappa": 5e5, "gamma": 1e2, **material})
    return MicropolarProblem(domain, mat, prefix=f"blk{id(domain)}_")


def _left(x):
    return np.isclose(x[0], 0.0)


def _right2(x):
    return np.isclose(x[0], 2.0)


def test_traction_and_couple_on_one_boundary_and_reactions():
    p = _block()
    p.fix(_left, "u")
    p.fix(_left, "phi")
    t, c = np.array([3e3, -2e3]), 50.0
    p.traction(_right2, t)
    p.surface_couple(_right2, c)
    p.traction(lambda x: np.isclose(x[0], 2.0) & (x[1] > 0.5 - 1e-12), (1e3, 0.0))  # overlaps
    p.solve()
    load = t * H + np.array([1e3 * 0.5, 0.0])
    assert p.reaction(_left, "u") == pytest.approx(-load, rel=1e-10)
    assert p.reaction(_left, "u_y") == pytest.approx(-load[1], rel=1e-10)
    # moment equilibrium about the origin: traction t_y at x = 2, t_x over y in [0, 1]
    # (lever arm y), the extra x-traction over y in [0.5, 1], and the couple
    applied = 2.0 * t[1] * H - t[0] * H**2 / 2 - 1e3 * (1.0 - 0.25) / 2 + c * H
    assert p.reaction_moment(_left) == pytest.approx(-applied, rel=1e-9)
    about = (0.0, 0.5)
    assert p.reaction_moment(_left, about) == pytest.approx(
        -applied - (about[1] * load[0]), rel=1e-9)


def test_pure_traction_held_at_points():
    """Equal and opposite tractions, held against rigid motion by point constraints: the
    homogeneous plane-strain answer, exact in the element."""
    p = _block()
    T = 1e4
    p.traction(_left, (-T, 0.0))
    p.traction(_right2, (T, 0.0))
    p.fix_point((0.0, 0.0), "u")
    p.fix_point((2.0, 0.0), "u_y")
    p.solve()
    mat = p.material
    mu_classical = mat.mu + mat.kappa / 2
    lam = mat.lam
    e_xx = T * (lam + 2 * mu_classical) / (4 * mu_classical * (lam + mu_classical))
    from granfe.probe import probe

    ux = probe(p.w.sub(0).collapse(), np.array([[2.0, 0.5, 0.0]]))[0, 0]
    assert ux == pytest.approx(2.0 * e_xx, rel=1e-9)
    with pytest.raises(ValueError, match="no u_x dof lies at the point"):
        p.fix_point((0.123, 0.456), "u_x")


def test_forest_constants_with_negative_eringen_mu_are_accepted():
    # Forest: classical shear modulus 1e6 Pa, Cosserat modulus mu_c = 3e6 Pa:
    # Eringen mu = mu_classical - mu_c = -2e6, kappa = 2 mu_c = 6e6, 2 mu + kappa = 2e6 > 0
    mat = MicropolarMaterial(lam=1e6, mu=-2e6, kappa=6e6, gamma=1.0)
    assert mat.mu + mat.kappa / 2 == pytest.approx(1e6)
    p = _block(mu=-2e6, kappa=6e6)
    p.fix(_left, "u")
    p.fix(_left, "phi")
    p.traction(_right2, (1e3, 0.0))
    p.solve()
    assert p.reaction(_left, "u_x") == pytest.approx(-1e3 * H, rel=1e-10)
    with pytest.raises(ValueError, match=r"MicropolarMaterial\.mu .* 2 mu \+ kappa > 0"):
        MicropolarMaterial(lam=1e6, mu=-2e6, kappa=3e6)
    MicropolarMaterial(lam=1.0, mu=1.0, kappa=0.1, beta=1.0, gamma=1.0)   # gamma = beta allowed


def test_import_granfe_then_dolfinx():
    code = "import granfe; import dolfinx; import petsc4py; print(dolfinx.__version__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_writer_outputs_fields_stresses_and_history(tmp_path):
    from granfe.io import ContinuumWriter

    p, d = _bar()
    d.value = 0.01
    p.solve()
    with ContinuumWriter(p, tmp_path, name="bar") as writer:
        writer.write(0.0)
        assert [path.name for path in writer.paths] == ["bar_fields.bp", "bar_stress.bp",
                                                        "bar_state.bp"]
        _, k = _closed_form(0.01, 0.0)
        assert np.allclose(writer.state["max_strain"].x.array, k, rtol=1e-12)
        sxx = writer.sigma.x.array.reshape(-1, 4)[:, 0]
        assert np.allclose(sxx, _closed_form(0.01, 0.0)[0] / H, rtol=1e-9)
    assert all(path.is_dir() for path in writer.paths)
