"""The flagship coupled runs tested as physics (STYLE 21), not as smoke.

1. A bonded elastic DE window inside the micropolar block gives the FE-only answer: the
   lattice's micropolar constants are exact for its bond energy
   (``test_staggered.py::test_lattice_constants_from_bond_energy``), so replacing part of the
   continuum by the lattice must leave the field unchanged up to the discretisation; and the
   staggered solve reaches that answer as its interface tolerance tightens.
2. A small coupled 2D cone penetration gives a tip resistance inside the scatter of full DEM
   over packings (the band of ``benchmarks/cpt_vs_full_dem.py``, rebuilt here on the same
   scene at its short settling time).
"""

from dataclasses import replace

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem

from coupling.apps.penetration.coupled import CoupledPenetration, DemPenetration, PenetrationParameters
from coupling.apps.punch.model import fe_block, lattice_block
from coupling.regions import Box, CouplingRegions
from coupling.staggered import StaggeredCoupling, StaggeredOptions
from dem.bonded import BondedAssembly, BondedSubproblem, find_bonds
from granfe.probe import probe

# ---- 1. bonded window == FE only ---------------------------------------------------------------
# a 0.2 m x 0.1 m block of bonded disks (the bonds of demos/2d/coupled_punch.py), base clamped,
# a smooth pressure hump (peak P0, width W) on its top; the window sits under the hump, two
# grain rows below the surface, where the field has its largest gradients
WIDTH, HEIGHT, RADIUS, KN, KT, KR_FACTOR = 0.2, 0.1, 0.002, 1.0e8, 3.0e7, 0.1
P0, W = 1.0e5, 0.02
H_FE = 0.01                           # P2/P2 elements
WINDOW_HALF_WIDTH, WINDOW_DEPTH, WINDOW_GAP = 0.04, 0.05, 0.02


def _block():
    return lattice_block(WIDTH, HEIGHT, RADIUS, KN, KT, KR_FACTOR, 2 * RADIUS)


def _loaded_block(comm, block, prefix):
    """The FE block of :func:`coupling.apps.punch.model.fe_block` under the pressure hump."""
    problem = fe_block(comm, block, H_FE, degree=(2, 2), prefix=prefix)
    xs = ufl.SpatialCoordinate(problem.domain)
    hump = P0 * ufl.exp(-(((xs[0] - block.centre) / W) ** 2))
    problem.traction(lambda p: np.isclose(p[1], block.surface), ufl.as_vector([0.0, -hump]))
    return problem


def bonded_window(comm, tol, prefix, kt_factor=1.0):
    """The coupled block: FE everywhere, a bonded window of grains under the hump. The
    grains' bonds may differ from the lattice the continuum's constants came from by
    ``kt_factor`` on kt (a wrong window, to show the comparison can fail)."""
    block = _block()
    problem = _loaded_block(comm, block, prefix)
    c, top = block.centre, block.surface - WINDOW_GAP
    window = Box((c - WINDOW_HALF_WIDTH, top - WINDOW_DEPTH), (c + WINDOW_HALF_WIDTH, top))
    regions = CouplingRegions(window, ghost_width=2.5 * 2 * RADIUS, handshake=H_FE)
    kinds = regions.particle_kinds(block.x)
    x, kinds = block.x[kinds >= 0], kinds[kinds >= 0]
    assembly = BondedAssembly(x, RADIUS, find_bonds(x, RADIUS), KN, KT * kt_factor, block.kr)
    particles = BondedSubproblem(assembly, np.flatnonzero(kinds == 1))
    coupling = StaggeredCoupling(problem, x, kinds, particles, regions,
                                 StaggeredOptions(tol=tol, max_iterations=500))
    coupling.solve()
    return coupling


def _displacement(problem):
    u = fem.Function(fem.functionspace(problem.domain, ("Lagrange", 2, (2,))))
    u.interpolate(problem.w.sub(0))
    return u


def probe_points(block):
    """The loaded surface's centre and flank, the window's centre, two far-field points."""
    c, s = block.centre, block.surface
    return np.array([[c, s, 0], [c + 0.05, s, 0], [c, s - 0.045, 0], [c + 0.08, 0.05, 0],
                     [c - 0.03, 0.03, 0]])


def differences(coupling, fe_only) -> tuple[float, float, float]:
    """Relative L2 difference of the free grains' displacements from the FE-only field at
    their centres; the largest FE displacement difference at the probe points over the
    largest FE-only value there; relative L2 difference of the grains' rotations from the
    FE-only micro-rotation phi at their centres."""
    free = coupling.kinds == 0
    u_ref = probe(_displacement(fe_only), coupling.x[free])
    grains = np.linalg.norm(coupling.u[free] - u_ref) / np.linalg.norm(u_ref)
    pts = probe_points(_block())
    a, b = probe(_displacement(coupling.problem), pts), probe(_displacement(fe_only), pts)
    phi = fem.Function(fem.functionspace(fe_only.domain, ("Lagrange", 2)))
    phi.interpolate(fe_only.w.sub(1))
    phi_ref = probe(phi, coupling.x[free]).ravel()
    spins = np.linalg.norm(np.ravel(coupling.theta)[free] - phi_ref) / np.linalg.norm(phi_ref)
    return float(grains), float(np.abs(a - b).max() / np.abs(b).max()), float(spins)


@pytest.fixture(scope="module")
def fe_only():
    problem = _loaded_block(MPI.COMM_WORLD, _block(), "flag_fe_only_")
    problem.solve()
    return problem


# The tolerances are the measured discretisation difference with a margin: at this mesh
# (P2, h = 5 grain diameters) the grains differ from the FE-only field by 6.6e-4 (L2) and
# the probes by 1.7e-4; halving the grain radius moves these only to 5.8e-4 / 1.3e-4 (the
# lattice's own error is small; the rest is the FE's interpolation of the grains' field),
# P1 elements give 1.4e-2 / 5e-3. A window whose kt is 10 % off the continuum's lattice
# gives 4.1e-3 / 2.0e-3, so 2e-3 / 6e-4 (3x the floor) separates a right window from a
# wrong one. (Wrong in kt / kn, i.e. in Poisson's ratio: scaling all bonds by one factor
# changes nothing, since the two sides exchange displacements only and each side's solve
# for given boundary displacements is blind to the scale of its own stiffness.) The
# grains' spins follow the continuum's micro-rotation to 9.6e-3 (phi is a derivative of the
# field: one order less accurate); 2e-2 checks that they do, it would not see a 10 % error
# in kt (1.2e-2).
GRAIN_TOL, PROBE_TOL, SPIN_TOL = 2e-3, 6e-4, 2e-2


def test_bonded_window_equals_fe_only(fe_only):
    """The coupled field (grains and continuum) equals the FE-only one under a load whose
    gradients run through the window."""
    coupling = bonded_window(MPI.COMM_WORLD, 1e-10, "flag_window_")
    grains, probes, spins = differences(coupling, fe_only)
    assert coupling.history[-1]["interface_residual"] < 1e-10
    assert grains < GRAIN_TOL, grains
    assert probes < PROBE_TOL, probes
    assert spins < SPIN_TOL, spins


def test_staggered_solve_converges_to_fe_only(fe_only):
    """Tightening the interface tolerance takes the coupled answer down to the FE-only one
    (to the discretisation floor of the test above): the error of a loose solve is the
    iteration's, a few times its tolerance (measured 3.4x at 1e-2 and 1e-3)."""
    errors = []
    for tol in (1e-2, 1e-3, 1e-5):
        coupling = bonded_window(MPI.COMM_WORLD, tol, f"flag_tol{tol:.0e}_")
        grains, _, _ = differences(coupling, fe_only)
        errors.append(grains)
        assert grains < 5 * tol + GRAIN_TOL, (tol, grains)
    assert errors[0] > errors[1] > errors[2]
    assert errors[0] > 10 * errors[2]


@pytest.mark.mpi
def test_bonded_window_two_ranks_equal_serial():
    """Under mpiexec -n 2 the distributed FE side gives the serial answer: the grains'
    displacements agree to round-off (measured 6e-12 relative, same iteration count), far
    below the physics tolerance."""
    comm = MPI.COMM_WORLD
    if comm.size == 1:
        pytest.skip("run under mpiexec -n 2")
    u = [bonded_window(c, 1e-10, f"flag_par{c.size}_").u for c in (comm, MPI.COMM_SELF)]
    assert np.abs(u[0] - u[1]).max() < 1e-9 * np.abs(u[1]).max()


# ---- 2. a small coupled CPT inside the full DEM band ------------------------------------------
# the 2D scene of benchmarks/cpt_vs_full_dem.py at its short settling time (GRANFE_SHORT): a
# 2 cm cone pushed 3 cm at 0.2 m/s into disks of 2 mm; full DEM fills the 0.2 m x 0.12 m
# chamber (1683 grains, walls), the coupled run has the window of half-width 6 cm (861 grains)
CPT = dict(chamber_width=0.2, chamber_depth=0.12, radius=2e-3, depth=0.03, velocity=0.2,
           settle_time=0.1, element_size_window=0.008, element_size_far=0.03,
           window_half_width=0.06, window_depth=0.08)
SEEDS = (1, 2)
SMOOTH = 0.005          # m, the benchmark's smoothing length of q_c
# The band. benchmarks/results/cpt_vs_full_dem.json (3 packings each, settled 0.3 s): one
# full-DEM packing's smoothed q_c differs from the packings' average by 19 % RMS
# (one_packing_rms_vs_average); the coupled windows' seed-averaged q_c differ from the
# full DEM's by 22-39 % RMS and their mean over the last half of the push by 2-33 %.
# With 2 packings a side and that scatter, the standard error of the difference of the two
# means is 19 % x sqrt(1/2 + 1/2) = 19 %: the tail means must agree within 2 of those
# (38 %), the smoothed curves within 50 % RMS (the benchmark's worst 39 %, with 2 packings
# instead of 3). Measured here (seeds 1, 2): tail 3749 vs 3923 Pa (-4 %), RMS 24 %; on 2
# ranks 4028 Pa (+3 %), RMS 26 % (one packing's tail moves 13 %, the other's 0.01 %, from
# serial: the grains' chaos amplifies the FE's round-off). The full DEM's own
# packings differ from their average by 12 % RMS, their tails by 6 %; the coupled run's
# tails scatter more (31 % over seeds 1-3: 4213, 3284, 6023 Pa), so 38 % is ~1.7 standard
# errors of a 2-packing coupled average: every pair of seeds 1-3 lies inside (-4, +19,
# +24 %). Frictionless grains give 1375 Pa (-65 %), RMS 66 %; the band does not see the
# continuum's stiffness (x 0.3: -15 %, x 3: +6 %; x 10 stops as CouplingUnstable).
PACKING_SCATTER = 0.19
TAIL_TOL = 2 * PACKING_SCATTER * np.sqrt(1 / len(SEEDS) + 1 / len(SEEDS))
RMS_TOL = 0.5


def smoothed(history) -> tuple[np.ndarray, np.ndarray]:
    """Depths and q_c smoothed over ``SMOOTH`` of depth (a running mean, as the benchmark)."""
    depth = np.array([h["depth"] for h in history])
    qc = np.array([h["q_c"] for h in history])
    k = max(1, int(round(SMOOTH / (depth[1] - depth[0]))))
    return depth, np.convolve(qc, np.ones(k) / k, mode="same")


def tail_mean(history) -> float:
    """Mean q_c over the last half of the push [Pa]."""
    return float(np.mean([h["q_c"] for h in history[len(history) // 2:]]))


def band_errors(coupled, full) -> tuple[float, float]:
    """Relative difference of the packing-averaged tail means, and relative RMS difference of
    the packing-averaged smoothed q_c once the tip is a third of its height into the grains
    (both against the full DEM, on the full DEM's depths)."""
    grid, _ = smoothed(full[0])
    ref = np.mean([np.interp(grid, *smoothed(h)) for h in full], axis=0)
    q = np.mean([np.interp(grid, *smoothed(h)) for h in coupled], axis=0)
    prm = PenetrationParameters(**CPT)
    embedded = grid > prm.cone_radius / np.tan(np.radians(prm.apex_deg) / 2) / 3
    rms = np.sqrt(np.mean((q - ref)[embedded] ** 2)) / np.sqrt(np.mean(ref[embedded] ** 2))
    dem_tail = np.mean([tail_mean(h) for h in full])
    tail = (np.mean([tail_mean(h) for h in coupled]) - dem_tail) / dem_tail
    return float(tail), float(rms)


def coupled_cpt(comm, **changes) -> list[list[dict]]:
    """Histories of the coupled scene, one per packing of ``SEEDS``."""
    prm = PenetrationParameters(**(CPT | changes))
    return [CoupledPenetration(replace(prm, seed=s), comm, log=lambda m: None).run() for s in SEEDS]


@pytest.fixture(scope="module")
def full_dem() -> list[list[dict]]:
    """The full DEM reference of the same scene, one history per packing of ``SEEDS``."""
    prm = PenetrationParameters(**CPT)
    return [DemPenetration(replace(prm, seed=s), log=lambda m: None).run() for s in SEEDS]


@pytest.mark.slow
@pytest.mark.mpi
def test_small_coupled_cpt_lies_in_the_full_dem_band(full_dem):
    """q_c against depth of the coupled scene, averaged over 2 packings, lies in the band of
    the full DEM's packing scatter; under mpiexec -n 2 (the FE distributed: a different
    round-off, so different grain trajectories) the same band holds."""
    coupled = coupled_cpt(MPI.COMM_WORLD)
    tail, rms = band_errors(coupled, full_dem)
    assert all(len(h) == len(full_dem[0]) for h in coupled)
    tails = [tail_mean(h) for h in coupled], [tail_mean(h) for h in full_dem]
    assert abs(tail) < TAIL_TOL, (tail, tails)
    assert rms < RMS_TOL, rms
