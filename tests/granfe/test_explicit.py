"""Explicit dynamics (granfe.explicit.CentralDifference): the measured stability limit is the
real one, a linear elastic body keeps its energy, the scheme is second order and reaches the
implicit answer as dt falls, the numba return mapping is the UFL one, a plastic step needs no
solve yet follows the implicit plastic run, a step may be solved again, and 2 ranks = 1."""

from dataclasses import replace

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh

from granfe.dynamics import GeneralizedAlpha
from granfe.explicit import CentralDifference, _FormForces, _LinearForces
from granfe.materials import MicropolarMaterial
from granfe.models.drucker_prager import DruckerPragerMaterial, MicropolarDruckerPrager
from granfe.models.micropolar import Micropolar
from granfe.problem import ContinuumProblem

ELASTIC = MicropolarMaterial.from_engineering(20e6, 0.25, length=0.02, kappa_over_mu=0.5,
                                              gamma_over_l2mu=1.0, rho=1600.0)
S0 = (-40e3, -40e3, -100e3)
PLASTIC = DruckerPragerMaterial(ELASTIC, 1e3, 30.0, 5.0, hardening=2e6, match="triaxial_compression",
                                initial_stress=S0)


def _at(axis, value):
    return lambda x: np.isclose(x[axis], value)


def block(model, n=(4, 4, 2), comm=MPI.COMM_WORLD, prefix="blk_"):
    """A 0.2 x 0.2 x 0.1 m block on a fixed base, rollers on the sides; returns the problem
    and the Dirichlet value of a square punch on the top (the dofs of u_z there)."""
    p = ContinuumProblem(mesh.create_box(comm, [[0, 0, 0], [0.2, 0.2, 0.1]], list(n)), model,
                         degree=(1, 1), prefix=prefix, solver="redundant",
                         petsc_options={"snes_rtol": 1e-14, "snes_atol": 1e-10})
    p.fix(_at(2, 0.0), "u")
    p.fix(_at(2, 0.0), "phi")
    for axis, name in ((0, "u_x"), (1, "u_y")):
        p.fix(_at(axis, 0.0), name)
        p.fix(_at(axis, 0.2), name)
    punch = lambda x: np.isclose(x[2], 0.1) & (x[0] < 0.06 + 1e-9) & (x[1] < 0.06 + 1e-9)  # noqa: E731
    return p, p.fix(punch, "u_z", 0.0)


def global_max(a, comm=MPI.COMM_WORLD):
    return comm.allreduce(float(np.abs(a).max()) if a.size else 0.0, MPI.MAX)


def free_vibration(stepper, steps):
    """Energies of a block released from a smooth initial displacement that its conditions
    allow (vertical, a quarter sine over the height: no kink at a boundary; no loads)."""
    p = stepper.problem
    V0 = p.V.sub(0).collapse()[0]
    u0 = fem.Function(V0)
    u0.interpolate(lambda x: np.stack([np.zeros_like(x[0]), np.zeros_like(x[0]),
                                       1e-4 * np.sin(np.pi * x[2] / 0.2)]))
    p.w.sub(0).interpolate(u0)
    for bc in p.bcs:
        bc.set(p.w.x.array)
    p.w.x.scatter_forward()
    stepper.initialize_acceleration()
    energy = []
    for _ in range(steps):
        stepper.step()
        energy.append(sum(stepper.energies()))
    return np.array(energy)


def test_measured_stability_limit_is_the_real_one():
    """At 0.95 of the measured limit (one substep) the free vibration's energy oscillates
    within 5 % (the scheme's O(h^2) error, largest near the limit) without drift; told the
    limit is 25 % longer than measured, the same run blows up: the measurement is neither
    unsafe nor far on the safe side."""
    p, _ = block(Micropolar(ELASTIC), prefix="lim_ok_")
    probe = CentralDifference(p, 1.0)
    dt = 0.95 * probe.critical_time_step
    stepper = CentralDifference(p, dt, safety=1.0)
    assert stepper.substeps_for(dt) == 1
    e = free_vibration(stepper, 400)
    assert np.all(np.abs(e / e[0] - 1) < 0.05), (e.min() / e[0], e.max() / e[0])
    assert e[-100:].mean() == pytest.approx(e[:100].mean(), rel=0.01)

    q, _ = block(Micropolar(ELASTIC), prefix="lim_bad_")
    wrong = CentralDifference(q, 1.25 * probe.critical_time_step, safety=1.0)
    wrong._omega_max = probe.omega_max / 1.25 / 1.001         # one substep at 1.25x the limit
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            e = free_vibration(wrong, 400)
            grown = e[-1] / e[0]
        except FloatingPointError:
            grown = np.inf
    assert not np.isfinite(grown) or grown > 1e3, grown


def test_mass_proportional_damping_takes_the_energy_at_its_rate():
    """Damping alpha (mass-proportional): the free vibration's energy decays as exp(-alpha t)
    (the slope of a log-linear fit within 5 % of -alpha, every mode alike), where the
    undamped run keeps it; the stability limit is 2 / omega_max (sqrt(1 + xi^2) - xi); a
    negative damping is refused, named."""
    dt_c = CentralDifference(block(Micropolar(ELASTIC), prefix="damp_probe_")[0], 1.0).critical_time_step
    dt, steps = 0.5 * dt_c, 400
    alpha = 2.0 / (steps * dt)                # e^-2 of the energy over the run
    p, _ = block(Micropolar(ELASTIC), prefix="damp_")
    stepper = CentralDifference(p, dt, damping=alpha)
    e = free_vibration(stepper, steps)
    slope = np.polyfit(dt * np.arange(1, steps + 1), np.log(e), 1)[0]
    assert slope == pytest.approx(-alpha, rel=0.05)
    assert e[-1] < 0.2 * e[0]
    xi = alpha / (2 * stepper.omega_max)
    assert stepper.critical_time_step == pytest.approx(dt_c * (np.sqrt(1 + xi**2) - xi), rel=1e-10)
    with pytest.raises(ValueError, match="damping"):
        CentralDifference(p, dt, damping=-1.0)


def _punched(stepper_of, dt, T, path, prefix):
    p, punch = block(Micropolar(ELASTIC), prefix=prefix)
    stepper = stepper_of(p, dt)
    for _ in range(int(round(T / dt))):
        punch.value = path(stepper.t + dt)
        stepper.step()
    return p.w.x.array.copy(), stepper


def test_second_order_and_close_to_the_implicit_run():
    """A punch pushed smoothly into the elastic block: at steps of a half and a quarter of
    the limit the explicit run closes on itself at a tiny step as dt^2, and the implicit run
    lies within 2 % of it (the lumped mass against the consistent one: a difference in
    space, not in time)."""
    dt_c = CentralDifference(block(Micropolar(ELASTIC), prefix="rate_probe_")[0], 1.0).critical_time_step
    T = 60 * dt_c

    def path(t):
        return -0.5e-4 * (1 - np.cos(np.pi * t / T))

    reference, _ = _punched(CentralDifference, dt_c / 16, T, path, "rate_ref_")
    implicit, _ = _punched(lambda p, dt: GeneralizedAlpha(p, dt, rho_inf=1.0), dt_c / 8, T, path, "rate_imp_")
    assert global_max(implicit - reference) < 0.02 * global_max(reference)
    errors = []
    for k in (2, 4):
        w, stepper = _punched(CentralDifference, dt_c / k, T, path, f"rate_{k}_")
        assert stepper.substeps == 1
        errors.append(global_max(w - reference) / global_max(reference))
    assert errors[0] < 0.02
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.25), errors


def test_a_long_step_is_its_substeps():
    """A step of 4.5 limits takes 5 substeps, the Dirichlet values moving linearly through
    them: with the punch at a constant speed it is the run of 5x as many steps, to
    round-off."""
    dt_c = CentralDifference(block(Micropolar(ELASTIC), prefix="sub_probe_")[0], 1.0).critical_time_step
    dt = 4.5 * dt_c
    T = 6 * dt

    def path(t):
        return -0.2 * t

    long, stepper = _punched(lambda p, h: CentralDifference(p, h, safety=1.0), dt, T, path, "sub_long_")
    assert stepper.substeps == 5
    short, stepper = _punched(lambda p, h: CentralDifference(p, h, safety=1.0), dt / 5, T, path, "sub_short_")
    assert stepper.substeps == 1
    assert global_max(long - short) <= 1e-12 * global_max(short)


def _points_and_ufl(gdim, material):
    """A plastic problem whose fields are random, its committed state from one random UFL
    return (so that points sit on, inside and beyond the cone, some past the apex)."""
    comm = MPI.COMM_SELF
    msh = (mesh.create_unit_square(comm, 3, 3) if gdim == 2 else mesh.create_unit_cube(comm, 2, 2, 2))
    p = ContinuumProblem(msh, MicropolarDruckerPrager(material), degree=(1, 1), prefix=f"pts{gdim}_")
    rng = np.random.default_rng(7)
    for _ in range(2):                                  # two commits: a history to return from
        p.w.x.array[:] = rng.normal(scale=2e-3, size=p.w.x.array.size)
        p.state.commit()
    p.w.x.array[:] += rng.normal(scale=2e-3, size=p.w.x.array.size)
    return p


def _plastic_block(n=(4, 4, 2), comm=MPI.COMM_WORLD, prefix="pb_"):
    return block(MicropolarDruckerPrager(PLASTIC), n=n, comm=comm, prefix=prefix)


def punch_history(stepper, settle, steps, speed=0.5):
    forces = []
    for _ in range(steps):
        settle.value = -speed * (stepper.t + float(stepper.dt.value))
        stepper.step()
        forces.append(-stepper.problem.reaction(
            lambda x: np.isclose(x[2], 0.1) & (x[0] < 0.06 + 1e-9) & (x[1] < 0.06 + 1e-9), "u_z"))
    return np.array(forces)


def test_plastic_explicit_follows_the_implicit_plastic_run():
    """The punched plastic block: the explicit run (no solve, the return once a substep) and
    the implicit one (quasi-Newton) at a quarter of the step agree on the punch force once
    the soil yields, within 2 % step by step (the waves in the block seen through the lumped
    and the consistent mass) and 0.5 % on average, and on the yielded share of the points."""
    dt = 4e-4
    p, settle = _plastic_block(prefix="pe_")
    explicit = CentralDifference(p, dt)
    f_exp = punch_history(explicit, settle, 20)
    q, settle_q = _plastic_block(prefix="pi_")
    implicit = GeneralizedAlpha(q, dt / 4, rho_inf=1.0)
    f_imp = punch_history(implicit, settle_q, 80)[3::4]
    assert explicit.substeps >= 2
    comm = MPI.COMM_WORLD
    share = [comm.allreduce(float(x.state.owned("yielding").sum()), MPI.SUM)
             / comm.allreduce(x.state.owned("yielding").size, MPI.SUM) for x in (p, q)]
    assert share[0] > 0.05 and abs(share[0] - share[1]) < 0.02, share
    assert np.abs(f_exp[10:] / f_imp[10:] - 1).max() < 0.02, (f_exp[10:], f_imp[10:])
    assert f_exp[10:].mean() == pytest.approx(f_imp[10:].mean(), rel=0.005)


def test_a_step_solved_again_is_the_same_step():
    """solve() after solve() (a staggered coupling's iterations) starts again from the step's
    start: the same fields and state, bit for bit; a failed solve leaves the step's start."""
    p, settle = _plastic_block(prefix="again_")
    stepper = CentralDifference(p, 2e-4)
    for _ in range(4):
        settle.value = -0.5 * (stepper.t + 2e-4)
        stepper.step()
    stepper.predict()
    settle.value = -0.5 * (stepper.t + 2e-4)
    stepper.solve()
    first = p.w.x.array.copy(), {k: f.x.array.copy() for k, f in p.state.committed.items()}
    stepper.solve()
    assert np.array_equal(p.w.x.array, first[0])
    for k, f in p.state.committed.items():
        assert np.array_equal(f.x.array, first[1][k]), k
    start = stepper.w_old.x.array.copy()
    settle.value = np.nan
    with pytest.raises(FloatingPointError, match="non-finite"):
        stepper.solve()
    assert np.array_equal(p.w.x.array, start)


def test_bad_arguments_are_named():
    p, _ = block(Micropolar(ELASTIC), n=(1, 1, 1), prefix="bad_")
    with pytest.raises(ValueError, match="dt"):
        CentralDifference(p, -1.0)
    with pytest.raises(ValueError, match="safety"):
        CentralDifference(p, 1e-4, safety=1.5)
    with pytest.raises(ValueError, match="max_substeps"):
        CentralDifference(p, 1.0, max_substeps=10).substeps_for(1.0)
    q = ContinuumProblem(mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1), Micropolar(ELASTIC),
                         degree=(2, 1), prefix="bad2_")
    with pytest.raises(ValueError, match="degree-1"):
        CentralDifference(q, 1e-4)


@pytest.mark.mpi
def test_explicit_plastic_on_two_ranks_is_serial():
    """The punched plastic block on the ranks of COMM_WORLD and on one rank: the same punch
    forces and the same largest displacement to round-off."""
    runs = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        p, settle = _plastic_block(comm=comm, prefix=f"rk{comm.size}_")
        forces = punch_history(CentralDifference(p, 2e-4), settle, 8)
        runs.append((forces, comm.allreduce(float(np.abs(p.w.x.array).max()), MPI.MAX)))
    (fa, wa), (fb, wb) = runs
    assert np.abs(fa - fb).max() <= 1e-10 * np.abs(fb).max()
    assert wa == pytest.approx(wb, rel=1e-10)


@pytest.mark.mpi
def test_an_elastic_residual_is_its_stiffness_times_w():
    """An elastic body's forces are ``K w - L`` (K assembled once, a product a substep): the
    UFL residual to round-off, with a partition weight, a surface traction and nodal loads,
    and after the load changes; the stiffness is assembled again when a modulus changes; a
    prestressed model keeps the UFL residual."""
    p, _ = block(Micropolar(ELASTIC), n=(3, 3, 2), prefix="lin_")
    V0 = fem.functionspace(p.domain, ("DG", 0))
    weight = fem.Function(V0)
    weight.interpolate(lambda x: np.where(x[0] < 0.1, 1e-6, 1.0))
    p.set_weight(weight)
    traction = fem.Constant(p.domain, np.array([0.0, 0.0, -1e3]))
    p.traction(_at(2, 0.1), traction)
    nodal = p.nodal_load("u")
    assert _LinearForces.fits(p)
    fast, slow = _LinearForces(p), _FormForces(p)
    rng = np.random.default_rng(3)
    p.w.x.array[:] = 1e-4 * rng.standard_normal(p.w.x.array.size)
    p.w.x.scatter_forward()
    b_fast, b_slow = fem.Function(p.V), fem.Function(p.V)

    def agree():
        fast.residual(b_fast.x.petsc_vec, commit=True)
        slow.residual(b_slow.x.petsc_vec, commit=True)
        # owned and ghost entries alike (the acceleration is taken on both)
        return global_max(b_fast.x.array - b_slow.x.array) / global_max(b_slow.x.array)

    for load in (1.0, -3.0):
        traction.value[2] = -1e3 * load
        nodal.set(load * rng.standard_normal(p.w.x.array.size))
        fast.start()
        assert agree() <= 1e-11
    K = fast.K
    p.model.update(replace(ELASTIC, mu=2 * ELASTIC.mu))
    fast.start()
    assert fast.K is not K
    assert agree() <= 1e-11
    # a term without w in the internal work (a prestress) is not K w: the UFL residual then
    prestress = fem.Constant(p.domain, 1e3)

    class Prestressed(Micropolar):
        def internal_work(self, w, dw, state):
            return super().internal_work(w, dw, state) + prestress * ufl.div(dw[0])

    q, _ = block(Prestressed(ELASTIC), n=(1, 1, 1), prefix="pre_")
    assert not _LinearForces.fits(q)
    assert isinstance(CentralDifference(q, 1e-4)._forces, _FormForces)


@pytest.mark.mpi
def test_explicit_elastic_runs_are_reproducible_and_serial():
    """The punched elastic block (the product's path): two runs on the ranks of COMM_WORLD
    give the same bits, and the one-rank run the same forces to round-off."""
    runs = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_WORLD, MPI.COMM_SELF):
        p, settle = block(Micropolar(ELASTIC), comm=comm, prefix=f"el{len(runs)}_")
        stepper = CentralDifference(p, 2e-4)
        assert isinstance(stepper._forces, _LinearForces)
        runs.append(punch_history(stepper, settle, 8))
    assert np.array_equal(runs[0], runs[1])
    assert np.abs(runs[0] - runs[2]).max() <= 1e-10 * np.abs(runs[2]).max()


@pytest.mark.parametrize("gdim", [2, 3])
@pytest.mark.parametrize("hardening", [2e6, -1e6, 0.0])
def test_fused_kernel_is_the_ufl_return_and_residual(gdim, hardening):
    """The fused kernel (kinematics, the numba return and the element forces in one pass
    over the cells) gives the residual dolfinx assembles from the UFL return, with a
    partition weight and a load, and the UFL return's state, to round-off, at points
    elastic and on the cone (hardening; softening to the floor; perfectly plastic)."""
    from granfe.explicit import _FormForces, _SimplexForces

    material = replace(PLASTIC, hardening=hardening, residual_cohesion=200.0 if hardening < 0 else 0.0,
                       match="plane_strain" if gdim == 2 else "triaxial_compression",
                       initial_stress=(-60e3, -100e3, -60e3) if gdim == 2 else S0)
    results = []
    for kind in (_FormForces, _SimplexForces):
        p = _points_and_ufl(gdim, material)
        DG0 = fem.functionspace(p.domain, ("DG", 0))
        weight = fem.Function(DG0)
        weight.interpolate(lambda x: 0.2 + x[0])
        p.set_weight(weight)
        p.body_force(np.full(gdim, -1e4))
        forces = kind(p)
        forces.start()
        b = fem.Function(p.V)
        forces.residual(b.x.petsc_vec, commit=True)
        forces.finish()
        results.append((b.x.array.copy(), {k: f.x.array.copy() for k, f in p.state.committed.items()}))
    (r0, s0), (r1, s1) = results
    yielding, eq = s0["yielding"], s0["equivalent_plastic_strain"]
    assert 0.1 < yielding.mean() < 0.95 and eq.max() > 0, yielding.mean()
    assert np.abs(r1 - r0).max() <= 1e-10 * np.abs(r0).max()
    for k in s0:
        assert np.abs(s1[k] - s0[k]).max() <= 1e-9 * max(np.abs(s0[k]).max(), 1e-12), k


def test_weighted_energies_split_the_body():
    """Energies weighted by a region's indicator and by its complement add up to the whole
    weighted by one (the kinetic energy of the consistent mass there; the unweighted one is
    the lumped mass's, the same stored energy)."""
    p, _ = block(Micropolar(ELASTIC), prefix="energy_")
    stepper = CentralDifference(p, 0.5 * CentralDifference(p, 1.0).critical_time_step)
    free_vibration(stepper, 20)
    x = ufl.SpatialCoordinate(p.domain)
    left = ufl.conditional(x[0] < 0.1, 1.0, 0.0)
    a, b = stepper.energies(left), stepper.energies(1 - left)
    whole, lumped = stepper.energies(ufl.as_ufl(1.0)), stepper.energies()
    assert a[0] + b[0] == pytest.approx(whole[0], rel=1e-10)
    assert a[1] + b[1] == pytest.approx(whole[1], rel=1e-10)
    assert whole[1] == pytest.approx(lumped[1], rel=1e-10)
    assert 0 < a[0] < whole[0] and 0 < a[1] < whole[1]
