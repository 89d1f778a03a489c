"""Biot u-p poroelasticity: Terzaghi and Mandel against their closed forms (with the
Mandel-Cryer effect), the undrained (Skempton B) and drained limits, fluxes and prescribed
pressures, the micropolar skeleton, bad input, and serial == mpiexec -n 2.

Physics tolerances: 1 % of the initial pore pressure (and of the settlement) at the meshes
and steps below; the backward-Euler time error dominates (measured: it halves when the
steps are halved). Limits that lie in the discrete space (uniform undrained pressure,
drained state, conservation of the fluid volume) are checked to round-off.
"""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh

from granfe.consolidation import (
    Consolidation,
    mandel_pressure,
    mandel_top_displacement,
    terzaghi_p0,
    terzaghi_pressure,
    terzaghi_settlement,
    time_grid,
)
from granfe.materials import MicropolarMaterial
from granfe.models.micropolar import Micropolar
from granfe.models.poroelastic import (
    MicropolarPoroelastic,
    MicropolarPoroelasticMaterial,
    PoreFluid,
    Poroelastic,
    PoroelasticMaterial,
)
from granfe.probe import probe
from granfe.problem import ContinuumProblem

FLUID = PoreFluid(k=1e-12, mu_f=1e-3, alpha=0.8, M=5e7)
SOIL = PoroelasticMaterial.from_engineering(1e7, 0.25, FLUID)
H, W, Q = 1.0, 0.1, 1e4           # column height, width [m], load [Pa]


def _close(value):
    return lambda x: np.isclose(x[1 if value[0] == "y" else 0], value[1])


def terzaghi_column(comm=MPI.COMM_WORLD, ny=40, model=None, prefix="tz", cell_type=mesh.CellType.triangle):
    """A column of height H in uniaxial strain, drained and loaded on top."""
    domain = mesh.create_rectangle(comm, [[0, 0], [W, H]], [1, ny], cell_type=cell_type)
    problem = ContinuumProblem(domain, model or Poroelastic(SOIL), prefix=f"{prefix}{id(domain)}_")
    problem.fix(_close(("y", 0.0)), "u_y")
    problem.fix(lambda x: np.isclose(x[0], 0) | np.isclose(x[0], W), "u_x")
    problem.fix(_close(("y", H)), "p")
    problem.traction(_close(("y", H)), (0.0, -Q))
    return problem


def column_sample(problem, ys):
    pts = np.c_[np.full_like(ys, W / 2), ys, np.zeros_like(ys)]
    p = probe(problem.w.sub(len(problem.fields) - 1).collapse(), pts)[:, 0]
    settlement = -probe(problem.w.sub(0).collapse(), np.array([[W / 2, H, 0.0]]))[0, 1]
    return p, settlement


def test_terzaghi_pressure_profile_and_settlement():
    problem = terzaghi_column()
    run = Consolidation(problem)
    run.undrained()
    c, p0 = SOIL.c_oedometric, terzaghi_p0(Q, SOIL)
    tc = H**2 / c
    ys = np.linspace(0, H, 81)
    p, _ = column_sample(problem, ys)
    assert np.allclose(p, p0, rtol=1e-10)       # undrained: uniform, the drained face too
    outputs = [0.01, 0.05, 0.1, 0.2, 0.5, 1.0]
    errors = []
    for T in time_grid(1.0, 200, 3.0, outputs):
        run.step(T * tc - run.t)
        if np.any(np.isclose(T, outputs)):
            p, s = column_sample(problem, ys)
            exact = terzaghi_pressure(H - ys, run.t, H=H, p0=p0, c=c)
            s_exact = terzaghi_settlement(run.t, H=H, q=Q, material=SOIL)
            errors.append((T, np.abs(p - exact).max() / p0, abs(s / s_exact - 1)))
    assert len(errors) == len(outputs)
    for T, e_p, e_s in errors:                   # measured: <= 0.54 %, <= 0.18 %
        assert e_p < 0.01 and e_s < 0.01, (T, e_p, e_s)


def test_terzaghi_time_error_is_first_order():
    """Backward Euler: halving the steps halves the error (at T = 0.2, 20 vs 40 uniform steps)."""
    c, p0 = SOIL.c_oedometric, terzaghi_p0(Q, SOIL)
    ys = np.linspace(0, H, 41)
    errors = []
    for n in (20, 40):
        problem = terzaghi_column(ny=80)
        run = Consolidation(problem)
        run.undrained()
        for _ in range(n):
            run.step(0.2 * H**2 / c / n)
        p, _ = column_sample(problem, ys)
        errors.append(np.abs(p - terzaghi_pressure(H - ys, run.t, H=H, p0=p0, c=c)).max() / p0)
    assert 1.7 < errors[0] / errors[1] < 2.3, errors


def test_drained_limit():
    """A step much longer than the consolidation time ends drained: p = 0 and the settlement
    of the drained constrained modulus."""
    problem = terzaghi_column(ny=10)
    run = Consolidation(problem)
    run.undrained()
    run.step(1e6 * H**2 / SOIL.c_oedometric)
    p, s = column_sample(problem, np.linspace(0, H, 11))
    assert np.abs(p).max() < 1e-6 * Q
    assert s == pytest.approx(Q * H / SOIL.oedometric_modulus, rel=1e-6)


# ---- Mandel ---------------------------------------------------------------------------------
MANDEL = PoroelasticMaterial.from_engineering(1e7, 0.1, PoreFluid(k=1e-12, mu_f=1e-3, alpha=1.0, M=1e9))
A = B_HALF = 1.0
F = 1e4                              # force on the quarter's plate [N/m]


def mandel_quarter(n=12):
    """The quarter 0 < x < a, 0 < y < b: symmetry on x = 0 and y = 0 (impermeable), the
    side x = a free and drained, the top a rigid frictionless impermeable plate. The mesh
    is graded to half size at the drained side (the early boundary layer)."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [A, B_HALF]], [n, n])
    xi = domain.geometry.x[:, 0] / A
    domain.geometry.x[:, 0] = A * (xi + 0.5 * xi * (1 - xi))
    problem = ContinuumProblem(domain, Poroelastic(MANDEL), prefix=f"mandel{id(domain)}_")
    problem.fix(lambda x: np.isclose(x[0], 0), "u_x")
    problem.fix(lambda x: np.isclose(x[1], 0), "u_y")
    problem.fix(lambda x: np.isclose(x[0], A), "p")
    plate = problem.fix(lambda x: np.isclose(x[1], B_HALF), "u_y", 0.0)
    return problem, plate


def test_mandel_pressure_plate_and_cryer_effect():
    problem, plate = mandel_quarter()
    run = Consolidation(problem)
    top = lambda x: np.isclose(x[1], B_HALF)  # noqa: E731
    run.step_with_resultant(0.0, plate, top, "u_y", -F)
    assert problem.reaction(top, "u_y") == pytest.approx(-F, rel=1e-10)
    c = MANDEL.c_mandel
    tc = A**2 / c
    p0 = F * MANDEL.B * (1 + MANDEL.nu_u) / (3 * A)
    xs = np.linspace(0, A, 41)
    pts = np.c_[xs, np.full_like(xs, 0.5 * B_HALF), np.zeros_like(xs)]
    pressure = lambda: probe(problem.w.sub(1).collapse(), pts)[:, 0]  # noqa: E731
    assert np.allclose(pressure(), p0, rtol=1e-9)            # undrained: uniform B (1 + nu_u) F / 3a
    undrained = -F * (1 - MANDEL.nu_u) * B_HALF / (2 * MANDEL.G * A)
    assert plate.value == pytest.approx(undrained, rel=1e-10)
    assert mandel_top_displacement(1e-9 * tc, a=A, b=B_HALF, F=F, material=MANDEL,
                                   terms=2000) == pytest.approx(undrained, rel=1e-3)
    outputs = [0.02, 0.05, 0.1, 0.2, 0.5, 1.0]
    errors, centre = [], []
    for T in time_grid(1.0, 150, 3.0, outputs):
        run.step_with_resultant(T * tc - run.t, plate, top, "u_y", -F)
        p = pressure()
        centre.append((T, p[0] / p0, mandel_pressure(0.0, run.t, a=A, F=F, material=MANDEL) / p0))
        if np.any(np.isclose(T, outputs)):
            exact = mandel_pressure(xs, run.t, a=A, F=F, material=MANDEL)
            d = mandel_top_displacement(run.t, a=A, b=B_HALF, F=F, material=MANDEL)
            errors.append((T, np.abs(p - exact).max() / p0, abs(plate.value / d - 1)))
    assert len(errors) == len(outputs)
    for T, e_p, e_u in errors:                   # measured: <= 0.45 %, <= 0.10 %
        assert e_p < 0.01 and e_u < 0.01, (T, e_p, e_u)
    T, fe, exact = np.array(centre).T
    late = T >= 0.01
    assert np.abs(fe - exact)[late].max() < 0.01
    # Mandel-Cryer: the centre pressure first rises above the undrained value (exact peak
    # 1.132 p0 at T = 0.077 for these constants), then decays
    assert fe.max() == pytest.approx(exact.max(), abs=0.005) and fe.max() > 1.1
    assert T[fe.argmax()] == pytest.approx(T[exact.argmax()], rel=0.2)
    assert fe[-1] < 0.4 * fe.max()


# ---- undrained limit, fluxes, pressures -------------------------------------------------------
@pytest.mark.mpi
@pytest.mark.parametrize("M", [5e7, np.inf])
def test_undrained_isotropic_load_gives_skempton_B(M):
    """A cube under an isotropic total stress applied undrained: p = B ds everywhere, the
    volumetric strain that of the undrained bulk modulus (M = inf: incompressible, zero)."""
    material = PoroelasticMaterial.from_engineering(1e7, 0.25, PoreFluid(k=1e-12, alpha=0.8, M=M))
    domain = mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    problem = ContinuumProblem(domain, Poroelastic(material), prefix=f"skempton{id(domain)}_")
    ds = 1e4
    for i, name in enumerate("xyz"):
        problem.fix(lambda x, i=i: np.isclose(x[i], 0), f"u_{name}")
        n = np.zeros(3)
        n[i] = 1.0
        problem.traction(lambda x, i=i: np.isclose(x[i], 1), -ds * n)
    problem.fix(lambda x: np.isclose(x[0], 1), "p")           # drained face: no effect at t = 0+
    Consolidation(problem).undrained()
    pts = np.array([[0.1, 0.2, 0.3], [0.9, 0.5, 0.5], [1.0, 1.0, 1.0]])
    p = probe(problem.w.sub(1).collapse(), pts)[:, 0]
    u = probe(problem.w.sub(0).collapse(), pts)
    assert np.allclose(p, material.B * ds, rtol=1e-10)
    assert material.B == pytest.approx(1 / 0.8 if np.isinf(M) else 0.8 * M / (material.K + 0.64 * M))
    strain = 0.0 if np.isinf(M) else -ds / (3 * material.K_u)
    assert np.allclose(u, strain * pts, atol=1e-12 * ds / material.K)


def test_undrained_plane_strain():
    """Plane strain, in-plane isotropic load ds: p = alpha M ds / (lam + mu + alpha^2 M)."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 3, 3)
    problem = ContinuumProblem(domain, Poroelastic(SOIL), prefix=f"ps{id(domain)}_")
    problem.fix(lambda x: np.isclose(x[0], 0), "u_x")
    problem.fix(lambda x: np.isclose(x[1], 0), "u_y")
    problem.traction(lambda x: np.isclose(x[0], 1), (-1e4, 0.0))
    problem.traction(lambda x: np.isclose(x[1], 1), (0.0, -1e4))
    Consolidation(problem).undrained()
    p = probe(problem.w.sub(1).collapse(), np.array([[0.3, 0.7, 0.0]]))[0, 0]
    f = SOIL.fluid
    assert p == pytest.approx(f.alpha * f.M * 1e4 / (SOIL.lam + SOIL.mu + f.alpha**2 * f.M), rel=1e-10)


def _rigid_box(material, n=4):
    domain = mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    problem = ContinuumProblem(domain, Poroelastic(material), prefix=f"box{id(domain)}_")
    problem.fix(lambda x: np.full(x.shape[1], True), "u")
    return problem


def test_inflow_is_conserved():
    """Inflow q through the left side of a rigid, otherwise sealed box: the stored fluid
    volume int p/M dx equals q L t (to round-off: mass is conserved exactly)."""
    problem = _rigid_box(SOIL)
    run = Consolidation(problem)
    inflow = run.flux(lambda x: np.isclose(x[0], 0), 1e-7)
    for _ in range(3):
        run.step(10.0)
    inflow.value = 2e-7
    run.step(10.0)
    pts = np.array([[0.0, 0.5, 0.0], [1.0, 0.5, 0.0]])
    stored = problem.domain.comm.allreduce(fem.assemble_scalar(fem.form(
        problem.split(problem.w)[1] * SOIL.fluid.inv_M * ufl.dx)), MPI.SUM)
    assert stored == pytest.approx(1e-7 * 30 + 2e-7 * 10, rel=1e-10)
    p = probe(problem.w.sub(1).collapse(), pts)[:, 0]
    assert p[0] > p[1] > 0                   # the fluid spreads from the inflow side


@pytest.mark.mpi
def test_prescribed_pressure_is_reached():
    """A pressure held on one side of a rigid box fills it up to that pressure, and the
    recorded inflow through that side is the fluid stored."""
    problem = _rigid_box(SOIL)
    problem.fix(lambda x: np.isclose(x[0], 0), "p", 2e3)
    run = Consolidation(problem)
    run.undrained()
    assert np.abs(problem.w.sub(1).collapse().x.array).max() < 1e-8   # not imposed at t = 0+
    run.monitor_inflow("left", lambda x: np.isclose(x[0], 0))
    entered = 0.0
    for dt in (1.0, 3.0, 10.0):
        run.step(dt)
        entered += dt * run.inflows["left"]
    stored = problem.domain.comm.allreduce(fem.assemble_scalar(fem.form(
        problem.split(problem.w)[1] * SOIL.fluid.inv_M * ufl.dx)), MPI.SUM)
    assert entered == pytest.approx(stored, rel=1e-10)                 # mass is conserved
    p1 = probe(problem.w.sub(1).collapse(), np.array([[1.0, 0.5, 0.0]]))[0, 0]
    run.step(1e9)
    p = problem.w.sub(1).collapse().x.array
    assert 0 < p1 < 2e3 and np.allclose(p, 2e3, rtol=1e-8)


# ---- micropolar skeleton ----------------------------------------------------------------------
def test_micropolar_skeleton_in_uniaxial_strain_equals_classical():
    """Uniaxial strain rotates nothing: a micropolar skeleton (kappa > 0) consolidates as the
    classical one of shear modulus mu + kappa / 2."""
    skeleton = MicropolarMaterial(lam=SOIL.lam, mu=SOIL.mu - 0.25 * SOIL.mu, kappa=0.5 * SOIL.mu,
                                  gamma=1e3)
    mp = MicropolarPoroelasticMaterial(skeleton, FLUID)
    assert mp.G == pytest.approx(SOIL.mu) and mp.c_oedometric == pytest.approx(SOIL.c_oedometric)
    results = []
    for model in (Poroelastic(SOIL), MicropolarPoroelastic(mp)):
        problem = terzaghi_column(ny=12, model=model, prefix="mpc", cell_type=mesh.CellType.quadrilateral)
        if "phi" in problem.components:
            problem.fix(_close(("y", 0.0)), "phi")
        run = Consolidation(problem)
        run.undrained()
        for _ in range(5):
            run.step(2.0)
        results.append(column_sample(problem, np.linspace(0, H, 7)))
    (p1, s1), (p2, s2) = results
    assert np.allclose(p1, p2, rtol=1e-9, atol=1e-9 * Q) and s1 == pytest.approx(s2, rel=1e-9)


# ---- bad input --------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, field", [
    ({"k": -1e-12}, "PoreFluid.k"),
    ({"k": 1e-12, "mu_f": 0.0}, "PoreFluid.mu_f"),
    ({"k": 1e-12, "alpha": 1.5}, "PoreFluid.alpha"),
    ({"k": 1e-12, "alpha": 0.0}, "PoreFluid.alpha"),
    ({"k": 1e-12, "M": -1.0}, "PoreFluid.M"),
    ({"k": float("nan")}, "PoreFluid.k"),
    ({"k": float("inf")}, "PoreFluid.k"),
])
def test_bad_fluid(kwargs, field):
    with pytest.raises(ValueError, match=field):
        PoreFluid(**kwargs)


def test_bad_material_and_use():
    with pytest.raises(ValueError, match="PoroelasticMaterial.mu"):
        PoroelasticMaterial(lam=1e6, mu=-1.0, fluid=FLUID)
    with pytest.raises(ValueError, match="PoroelasticMaterial.lam"):
        PoroelasticMaterial(lam=-1e6, mu=1e6, fluid=FLUID)
    with pytest.raises(TypeError, match="fluid must be a PoreFluid"):
        PoroelasticMaterial(lam=1e6, mu=1e6, fluid=1.0)
    with pytest.raises(ValueError, match="porosity"):
        PoreFluid.from_constituents(k=1e-12, mu_f=1e-3, porosity=1.2, K_f=2.2e9, K_drained=1e7)
    with pytest.raises(TypeError, match="PoroelasticMaterial"):
        Poroelastic(MicropolarMaterial(lam=1.0, mu=1.0, kappa=0.0))
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 1, 1)
    elastic = ContinuumProblem(domain, Micropolar(MicropolarMaterial(lam=1.0, mu=1.0, kappa=0.0)),
                               prefix="notbiot_")
    with pytest.raises(TypeError, match="Biot model"):
        Consolidation(elastic)
    run = Consolidation(_rigid_box(SOIL, 1))
    with pytest.raises(ValueError, match="dt"):
        run.step(-1.0)
    with pytest.raises(ValueError, match="dt"):
        run.model.set_time_step(float("nan"))
    with pytest.raises(ValueError, match="output times"):
        time_grid(1.0, 10, include=[2.0])


def test_constituents_give_biot_constants():
    """alpha = 1 - K/K_s, 1/M = n/K_f + (alpha - n)/K_s; incompressible grains: alpha = 1, M = K_f/n."""
    f = PoreFluid.from_constituents(k=1e-12, mu_f=1e-3, porosity=0.4, K_f=2.2e9, K_drained=1e8)
    assert f.alpha == 1.0 and f.M == pytest.approx(2.2e9 / 0.4)
    g = PoreFluid.from_constituents(k=1e-12, mu_f=1e-3, porosity=0.4, K_f=2.2e9, K_drained=1e9, K_s=4e10)
    assert g.alpha == pytest.approx(0.975)
    assert 1 / g.M == pytest.approx(0.4 / 2.2e9 + 0.575 / 4e10)


# ---- MPI -------------------------------------------------------------------------------------
@pytest.mark.mpi
def test_serial_equals_parallel():
    results = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        problem = terzaghi_column(comm, ny=16, prefix=f"tzmpi{comm.size}")
        run = Consolidation(problem)
        run.undrained()
        for dt in (1.0, 2.0, 4.0):
            run.step(dt)
        results.append(column_sample(problem, np.linspace(0, H, 9)))
    (pa, sa), (pb, sb) = results
    assert np.allclose(pa, pb, rtol=1e-10, atol=1e-10 * Q) and sa == pytest.approx(sb, rel=1e-10)
