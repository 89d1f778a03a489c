"""Micropolar Drucker-Prager: Mohr-Coulomb peaks in triaxial and plane-strain compression,
the flow rule's dilatancy, the consistent tangent (Taylor test), validation; the dynamic step
on the elastic Jacobian against Newton."""

import math

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh
from taylor import taylor_rates

from granfe.dynamics import GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.models.drucker_prager import (
    DruckerPragerMaterial,
    MicropolarDruckerPrager,
    drucker_prager_constants,
)
from granfe.probe import probe
from granfe.problem import ContinuumProblem

ELASTIC = MicropolarMaterial.from_engineering(50e6, 0.25, length=0.01, kappa_over_mu=0.5,
                                              gamma_over_l2mu=1.0)
C = 10e3


def mohr_coulomb_peak(sigma3, phi_deg, c=C):
    t = math.tan(math.radians(45 + phi_deg / 2))
    return sigma3 * t**2 + 2 * c * t


def _at(axis, value):
    return lambda x: np.isclose(x[axis], value)


def triaxial(sigma3, phi=30.0, psi=10.0, n=1, comm=MPI.COMM_WORLD):
    """Unit cube, symmetry planes x = y = z = 0, confining traction on x = 1 and y = 1,
    the top z = 1 pushed down: homogeneous triaxial compression."""
    mat = DruckerPragerMaterial(ELASTIC, C, phi, psi, match="triaxial_compression")
    p = ContinuumProblem(mesh.create_unit_cube(comm, n, n, n), MicropolarDruckerPrager(mat),
                         degree=(1, 1), prefix=f"tri{n}_{int(sigma3)}_")
    for axis, name in enumerate(("u_x", "u_y", "u_z")):
        p.fix(_at(axis, 0.0), name)
    p.fix(lambda x: np.isclose(x[0], 0) | np.isclose(x[1], 0) | np.isclose(x[2], 0)
          | np.isclose(x[2], 1), "phi")
    p.traction(_at(0, 1.0), (-sigma3, 0.0, 0.0))
    p.traction(_at(1, 1.0), (0.0, -sigma3, 0.0))
    return p, p.fix(_at(2, 1.0), "u_z", 0.0), mat


@pytest.mark.parametrize("sigma3", [50e3, 100e3, 300e3])
def test_triaxial_peak_is_mohr_coulomb(sigma3):
    p, top, _ = triaxial(sigma3)
    axial = []
    for dz in (-5e-4, -1e-3, -2e-3, -4e-3, -8e-3, -0.015, -0.03):
        top.value = dz
        p.solve()
        axial.append(-p.reaction(_at(2, 1.0), "u_z"))
    assert max(axial) == pytest.approx(mohr_coulomb_peak(sigma3, 30.0), rel=1e-10)
    assert axial[0] < 0.9 * max(axial)                      # it starts elastic
    assert p.state.committed["yielding"].x.array.min() == 1.0


def test_triaxial_dilatancy_follows_the_flow_rule():
    p, top, mat = triaxial(100e3, phi=30.0, psi=10.0)
    _, B, _ = mat.constants
    corner = np.array([[1.0, 1.0, 1.0]])
    strains = []
    for dz in (-0.02, -0.025, -0.03):          # all past the peak (perfectly plastic)
        top.value = dz
        p.solve()
        u = probe(p.w.sub(0).collapse(), corner)[0]
        strains.append((u.sum(), u[2]))        # (volumetric, axial) strain of the unit cube
    (v1, a1), (v2, a2) = strains[1], strains[2]
    ratio = (v2 - v1) / (a2 - a1)
    assert ratio == pytest.approx(B / (B / 3 - 1 / math.sqrt(3)), rel=1e-8)
    assert ratio < 0                            # compression axially, dilation in volume


@pytest.mark.parametrize("psi", [0.0, 15.0, 30.0])
def test_plane_strain_match_reaches_mohr_coulomb(psi):
    """Biaxial plane-strain compression: with the plane-strain match the peak tends to
    Mohr-Coulomb's as the out-of-plane elastic strain rate dies out (it rises monotonically
    and is within 2e-4 after 10 % axial strain, for any dilatancy)."""
    mat = DruckerPragerMaterial(ELASTIC, C, 30.0, psi, match="plane_strain")
    p = ContinuumProblem(mesh.create_unit_square(MPI.COMM_WORLD, 1, 1),
                         MicropolarDruckerPrager(mat), degree=(1, 1), prefix=f"ps{int(psi)}_")
    p.fix(_at(0, 0.0), "u_x")
    p.fix(_at(1, 0.0), "u_y")
    p.fix(lambda x: np.isclose(x[0], 0) | np.isclose(x[1], 0) | np.isclose(x[1], 1), "phi")
    p.traction(_at(0, 1.0), (-100e3, 0.0))
    top = p.fix(_at(1, 1.0), "u_y", 0.0)
    axial = []
    for dz in np.linspace(0.0, -0.1, 21)[1:]:
        top.value = dz
        p.solve()
        axial.append(-p.reaction(_at(1, 1.0), "u_y"))
    mc = mohr_coulomb_peak(100e3, 30.0)
    assert axial[-1] == pytest.approx(mc, rel=2e-4)
    assert all(a <= mc * (1 + 1e-10) for a in axial)
    assert np.all(np.diff(axial) >= -1e-6 * mc)


def test_softening_stops_at_the_residual_cohesion():
    """Triaxial compression of a softening cone: the axial stress falls from at most the
    peak Mohr-Coulomb value to the residual one (cohesion c_r) and stays there exactly once
    the equivalent plastic strain has used up the softening range (k0 - k_r) / -H."""
    p, top, _ = triaxial(100e3)
    mat = DruckerPragerMaterial(ELASTIC, C, 30.0, 10.0, hardening=-4e5, residual_cohesion=C / 4,
                                match="triaxial_compression")
    p.model.update(mat)
    used_up = (mat.constants[2] - mat.residual_strength) / 4e5
    axial = []
    for dz in np.linspace(0.0, -0.05, 26)[1:]:
        top.value = dz
        p.solve()
        axial.append(-p.reaction(_at(2, 1.0), "u_z"))
    peak, residual = mohr_coulomb_peak(100e3, 30.0), mohr_coulomb_peak(100e3, 30.0, c=C / 4)
    assert max(axial) <= peak * (1 + 1e-10)
    assert p.state.committed["equivalent_plastic_strain"].x.array.min() > used_up
    assert axial[-1] == pytest.approx(residual, rel=1e-10)
    assert axial[-2] == pytest.approx(residual, rel=1e-10)
    softening = [a for a in axial if residual * (1 + 1e-6) < a < peak * (1 - 1e-6)]
    assert len(softening) >= 3 and np.all(np.diff(axial[np.argmax(axial):]) <= 1e-8 * peak)


@pytest.mark.mpi
def test_shear_band_width_is_set_by_the_cosserat_length(tmp_out, monkeypatch):
    """demos/2d/biaxial_shear_band.py, short (two coarse meshes, 12 and 16 elements across a
    100 mm specimen, l = 3 mm): the band forms after the peak, which is within 1 % of the
    homogeneous specimen's; with the couple terms its width changes by less than 10 %
    between the meshes and is more than twice the width without them, which shrinks by more
    than 15 % with the elements; the Cosserat band lies between the Roscoe and Coulomb
    inclinations."""
    import runpy
    import sys
    from pathlib import Path

    demo = Path(__file__).resolve().parents[2] / "demos" / "2d" / "biaxial_shear_band.py"
    monkeypatch.setenv("GRANFE_SHORT", "1")
    monkeypatch.setattr(sys, "argv", [str(demo), "--out", str(tmp_out)])          # 12, 16 elements
    results = runpy.run_path(str(demo), run_name="__main__")["results"]
    s, cosserat, classical = results["summary"], results["cosserat"], results["classical"]
    homogeneous = results["homogeneous"]["peak_stress"]
    for run in cosserat:
        assert 0 <= 1 - run["peak_stress"] / homogeneous < 0.01
        profile = np.array(run["band"]["profile"][1])         # gained after the peak
        assert profile.min() < 0.2 * profile.max()              # ... in a band
    assert s["cosserat_width_spread"] < 0.10, s
    assert s["classical_width_ratio_coarse_to_fine"] > 1.15, s
    assert all(c["band"]["fwhm"] > 2 * k["band"]["fwhm"] for c, k in zip(cosserat, classical, strict=True))
    angles = s["band_angles_deg"]
    assert all(angles["roscoe"] < a < angles["coulomb"] for a in angles["cosserat"]), angles


def test_plane_strain_constants_are_the_textbook_ones_when_associated():
    A, B, k0 = drucker_prager_constants(30.0, 30.0, C, "plane_strain")
    t = math.tan(math.radians(30.0))
    assert A == pytest.approx(3 * t / math.sqrt(9 + 12 * t**2), rel=1e-14)
    assert B == pytest.approx(A, rel=1e-14)
    assert k0 == pytest.approx(3 * C / math.sqrt(9 + 12 * t**2), rel=1e-14)


def test_consistent_tangent_taylor():
    """|R(w + h dw) - R(w) - h J(w) dw| falls as h^2 in a plastic trial state with hardening
    (an inconsistent tangent gives h^1). Every point is well inside the plastic branch, so a
    small perturbation crosses no kink of the return mapping."""
    p, top, _ = triaxial(100e3, n=2)
    p.model.update(DruckerPragerMaterial(ELASTIC, C, 30.0, 10.0, hardening=2e6,
                                         match="triaxial_compression"))
    for dz in (-0.01, -0.02):
        top.value = dz
        p.solve()
    top.value = -0.025
    p.solve(commit=False)                         # a trial state past the committed one
    assert p.state.committed["yielding"].x.array.min() == 1.0
    rates = taylor_rates(p)
    assert np.all(rates > 1.8), rates


@pytest.mark.mpi
def test_triaxial_on_any_rank_count():
    p, top, _ = triaxial(100e3, n=2)
    for dz in np.linspace(0.0, -0.02, 6)[1:]:
        top.value = dz
        p.solve()
    assert -p.reaction(_at(2, 1.0), "u_z") == pytest.approx(mohr_coulomb_peak(100e3, 30.0),
                                                             rel=1e-10)


@pytest.mark.parametrize("kwargs, key", [
    (dict(cohesion=-1.0, friction_deg=30.0), "cohesion"),
    (dict(cohesion=1.0, friction_deg=95.0), "friction_deg"),
    (dict(cohesion=1.0, friction_deg=20.0, dilatancy_deg=25.0), "dilatancy_deg"),
    (dict(cohesion=1.0, friction_deg=20.0, match="triaxial"), "match"),
    (dict(cohesion=0.0, friction_deg=0.0), "no strength"),
    (dict(cohesion=1.0, friction_deg=20.0, residual_cohesion=2.0), "residual_cohesion"),
])
def test_material_is_validated(kwargs, key):
    with pytest.raises(ValueError, match=key):
        DruckerPragerMaterial(ELASTIC, **kwargs)
    with pytest.raises(ValueError, match="alpha and beta must be 0"):
        DruckerPragerMaterial(MicropolarMaterial(1.0, 1.0, 0.1, beta=0.1), 1.0, 20.0)


def test_initial_stress_confines_like_a_traction():
    """A uniform initial stress -sigma3 I with traction-free sides (the increment's boundary
    conditions) reaches the same Mohr-Coulomb peak as the confining traction sigma3 does:
    the yield function sees the total stress, the equations the increment."""
    sigma3 = 100e3
    mat = DruckerPragerMaterial(ELASTIC, C, 30.0, 10.0, match="triaxial_compression",
                                initial_stress=(-sigma3, -sigma3, -sigma3))
    p = ContinuumProblem(mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1), MicropolarDruckerPrager(mat),
                         degree=(1, 1), prefix="tri_s0_")
    for axis, name in enumerate(("u_x", "u_y", "u_z")):
        p.fix(_at(axis, 0.0), name)
    p.fix(lambda x: np.isclose(x[0], 0) | np.isclose(x[1], 0) | np.isclose(x[2], 0)
          | np.isclose(x[2], 1), "phi")
    top = p.fix(_at(2, 1.0), "u_z", 0.0)
    p.solve()
    np.testing.assert_allclose(p.w.x.array, 0.0, atol=1e-14)   # the initial state is in equilibrium
    axial = []
    for dz in (-5e-4, -1e-3, -2e-3, -4e-3, -8e-3, -0.015, -0.03):
        top.value = dz
        p.solve()
        axial.append(sigma3 - p.reaction(_at(2, 1.0), "u_z"))
    assert max(axial) == pytest.approx(mohr_coulomb_peak(sigma3, 30.0), rel=1e-9)
    with pytest.raises(ValueError, match="initial_stress .* lies outside the yield cone"):
        DruckerPragerMaterial(ELASTIC, 0.0, 30.0, initial_stress=(-1e5, -1e4, -1e4))


def test_apex_without_dilatancy_keeps_a_finite_plastic_strain():
    """Pulled apart, a cohesionless, non-dilatant cone (its apex stiffness K A B + H is zero)
    returns to the apex (stress free) with a finite equivalent plastic strain: the volumetric
    plastic strain, not a division by the vanishing stiffness."""
    mat = DruckerPragerMaterial(ELASTIC, 0.0, 30.0, 0.0, match="triaxial_compression")
    p = ContinuumProblem(mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1), MicropolarDruckerPrager(mat),
                         degree=(1, 1), prefix="apex_")
    for axis, name in enumerate(("u_x", "u_y", "u_z")):
        p.fix(_at(axis, 0.0), name)
        p.fix(_at(axis, 1.0), name, 1e-3)
    p.fix(lambda x: np.full(x.shape[1], True), "phi")
    p.solve()
    p.state.commit()
    for axis, name in enumerate(("u_x", "u_y", "u_z")):   # stress free: no force on the faces
        assert abs(p.reaction(_at(axis, 1.0), name)) < 1e-9 * ELASTIC.lam * 1e-3
    eq = p.state.owned("equivalent_plastic_strain")
    # volumetric plastic strain 3e-3 (all the strain: the stress is zero)
    np.testing.assert_allclose(eq, 3e-3, rtol=1e-9)


def punched_block(tangent, comm=MPI.COMM_WORLD):
    """A block under a compressive initial stress (bottom fixed, sides on rollers), a corner of
    its top pushed down, stepped in time with generalized-alpha: a few steps yield a part of
    the points under the punch. Tolerances far below the tests' (the answers are compared)."""
    elastic = MicropolarMaterial.from_engineering(50e6, 0.25, length=0.05, kappa_over_mu=0.5,
                                                  gamma_over_l2mu=1.0, rho=2000.0)
    mat = DruckerPragerMaterial(elastic, 1e3, 30.0, 5.0, hardening=2e6, match="triaxial_compression",
                                initial_stress=(-40e3, -40e3, -100e3))
    p = ContinuumProblem(mesh.create_box(comm, [[0, 0, 0], [1, 1, 0.5]], [4, 4, 2]),
                         MicropolarDruckerPrager(mat), degree=(1, 1), prefix=f"punch_{tangent}_",
                         petsc_options={"snes_rtol": 1e-14, "snes_atol": 1e-8})
    p.fix(_at(2, 0.0), "u")
    p.fix(_at(2, 0.0), "phi")
    for axis, name in ((0, "u_x"), (1, "u_y")):
        p.fix(_at(axis, 0.0), name)
        p.fix(_at(axis, 1.0), name)
    punch = lambda x: np.isclose(x[2], 0.5) & (x[0] < 0.3) & (x[1] < 0.3)  # noqa: E731
    return GeneralizedAlpha(p, 2e-3, rho_inf=0.8, tangent=tangent), p.fix(punch, "u_z", 0.0)


@pytest.mark.mpi
def test_dynamic_step_on_the_elastic_jacobian_is_newtons():
    """Quasi-Newton on the elastic Jacobian, factorised once (the default), reaches Newton's
    answer on the consistent tangent to the solver's tolerance, step by step through yielding
    and a change of dt; an elastic step takes one iteration; the Jacobian is assembled again
    only when dt changes."""
    runs = {}
    for tangent in ("consistent", "elastic"):
        stepper, settle = punched_block(tangent)
        history = []
        for k, dz in enumerate((-1e-6, -5e-4, -1.5e-3, -3e-3, -4.5e-3, -6e-3)):
            if k == 4:
                stepper.dt.value = 1e-3
            settle.value = dz
            history.append((stepper.step(), stepper.problem.w.x.array.copy()))
            if tangent == "elastic" and k == 1:
                state = stepper._snes.A.stateGet()
            if tangent == "elastic" and k in (3, 4):
                assert (stepper._snes.A.stateGet() == state) == (k == 3)   # dt changed at 4
        runs[tangent] = stepper, history
    (newton, ref), (quasi, got) = runs["consistent"], runs["elastic"]
    assert got[0][0] == 1                                  # the first step stays elastic
    assert quasi.fallbacks == 0 and max(its for its, _ in got) > 2
    comm = MPI.COMM_WORLD
    scale = comm.allreduce(float(np.abs(ref[-1][1]).max()), MPI.MAX)
    for (_, a), (_, b) in zip(ref, got, strict=True):
        assert comm.allreduce(float(np.abs(a - b).max()), MPI.MAX) < 1e-9 * scale
    yielding = quasi.problem.state.owned("yielding")
    share = comm.allreduce(float(yielding.sum()), MPI.SUM) / comm.allreduce(yielding.size, MPI.SUM)
    assert 0.02 < share < 0.9, share
    for name, f in newton.problem.state.committed.items():
        a, b = f.x.array, quasi.problem.state.committed[name].x.array
        size = comm.allreduce(float(np.abs(a).max()) if a.size else 0.0, MPI.MAX)
        assert comm.allreduce(float(np.abs(a - b).max()) if a.size else 0.0, MPI.MAX) <= 1e-7 * size, name
