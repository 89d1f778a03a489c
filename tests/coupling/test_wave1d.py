"""Axial waves through the 1D rod x spring-string overlap (seed 001 eq. 79-90, 108-121)."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.monolithic1d import AverageAcceleration, axial_overlap, particle_share
from dem.glued import SpringString
from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D

D = 0.01
A, I = np.pi * (D / 2) ** 2, np.pi * (D / 2) ** 4 / 4
MAT = MicropolarMaterial(5.8e9, 3.8e9, 0.38e9, gamma=2e3, rho=2500.0, j=D**2 / 8)
C = MAT.lam + 2 * MAT.mu + MAT.kappa
CW = np.sqrt(C / MAT.rho)


def _system(h_over_d, overlap, weighting="ramp", x_a=0.8, length=0.8):
    h = h_over_d * D
    x_b = x_a + overlap * h
    rod = Rod1D(MAT, x_b, A, I, round(x_b / h), MPI.COMM_SELF)
    string = SpringString(round(length / D) + 1, D, C * A / D, MAT.rho * A * D, x_a)
    return axial_overlap(rod, string, weighting)


def _pulse(system, w, xc=0.3, amplitude=1e-6):
    """Right-going cos^2 pulse of half-width w [m] run until it has left the overlap."""
    def u(x):
        return amplitude * np.where(np.abs(x - xc) < w, np.cos(np.pi * (x - xc) / (2 * w)) ** 2, 0)

    def v(x):  # -c u' for a right-going wave
        s = x - xc
        return CW * amplitude * np.where(np.abs(s) < w, np.pi / (2 * w) * np.sin(np.pi * s / w), 0)

    X, V = system.state(u, v)
    stepper = AverageAcceleration(system.M, system.K, 0.25 * D / CW)
    acc = stepper.initial_acceleration(X)
    E0 = system.energy(X, V)
    for _ in range(int((system.x_b + w + 0.05 - xc) / CW / stepper.dt)):
        X, V, acc = stepper.step(X, V, acc)
    return X, V, E0


def test_particle_share_is_a_partition_of_unity():
    s0, s1 = 1.0, 2.0
    assert particle_share(0.0, 1.0, s0, s1) == 0.0 and particle_share(2.0, 3.0, s0, s1) == 1.0
    assert particle_share(1.0, 2.0, s0, s1) == pytest.approx(0.5, abs=1e-15)
    assert particle_share(0.5, 1.5, 1.0, 1.0) == pytest.approx(0.5, abs=1e-15)  # step


@pytest.mark.parametrize("weighting", ["ramp", "volume", "volume_equal"])
def test_mass_is_partitioned_exactly(weighting):
    """Particles cover [x_a - d/2, end + d/2], the rod [0, x_b]: M counts each length once."""
    s = _system(2, 2, weighting)
    one = np.ones(s.M.shape[0])
    total = MAT.rho * A * (s.string.x[-1] + D / 2)
    assert one @ (s.M @ one) == pytest.approx(total, rel=1e-12)
    assert abs(s.K - s.K.T).max() < 1e-12 * abs(s.K).max()
    assert abs(s.K @ one).max() < 1e-9 * abs(s.K).max()  # rigid motion is free


@pytest.mark.parametrize("h_over_d, overlap, weighting, ghost", [
    (2, 0, "ramp", False), (2, 0, "volume", False), (1, 2, "volume", False),
    (1, 2, "ramp", False), (2, 2, "volume", True), (2, 2, "ramp", True)])
def test_patch_test(h_over_d, overlap, weighting, ghost):
    """Uniform strain leaves no interior force when the stiffness share steps at a particle
    centre and each prescribed node sits on one particle (abrupt, or h = d, where a cell's
    stiffness equals the spring's and any split of it is exact). Otherwise the
    FE traction at x_a reaches the particles through the projection P^T (spread over a cell)
    or the share varies (ramp): self-equilibrated ghost forces in the overlap."""
    s = _system(h_over_d, overlap, weighting)
    X = np.concatenate([s.string.x, s.u_x[s.free]])  # u = x: strain 1
    f = s.K @ X
    interior = np.ones(f.size, bool)
    interior[[s.string.n - 1, s.string.n + np.argmin(s.u_x[s.free])]] = False
    assert abs(f.sum()) < 1e-9 * C * A
    assert abs(f[interior]).max() > 1e-3 * C * A if ghost else abs(f[interior]).max() < 1e-9 * C * A


def test_energy_is_conserved_and_a_smooth_pulse_crosses():
    s = _system(2, 2)
    X, V, E0 = _pulse(s, 25 * D)
    assert abs(s.energy(X, V) - E0) < 1e-10 * E0  # no damping: exact up to round-off
    parts = sum(s.energy(X, V, r) for r in ("fe", "overlap", "de"))
    assert parts == pytest.approx(E0, rel=1e-10)
    # measured 9.5e-5 left behind (of which 2.3e-5 is FE dispersion), 0.9999 transmitted
    assert s.energy(X, V, "fe") < 3e-4 * E0
    assert s.energy(X, V, "de") > 0.999 * E0


def test_short_pulse_reflects_more_than_long_pulse():
    """A pulse much longer than d transmits almost fully; one of a few d does not."""
    s = _system(2, 2)
    fractions = {}
    for w_over_d in (3, 25):
        X, V, E0 = _pulse(s, w_over_d * D)
        fractions[w_over_d] = (s.energy(X, V, "fe") / E0, s.energy(X, V, "de") / E0)
    assert fractions[3][0] > 100 * fractions[25][0]
    assert fractions[3][1] < 0.95 < 0.999 < fractions[25][1]


def test_bad_input_is_named():
    rod = Rod1D(MAT, 0.1, A, I, 5, MPI.COMM_SELF)
    with pytest.raises(ValueError, match="weighting"):
        axial_overlap(rod, SpringString(20, D, 1.0, 1.0, 0.05), "linear")
    with pytest.raises(ValueError, match="string must start inside the rod"):
        axial_overlap(rod, SpringString(20, D, 1.0, 1.0, 0.15))
    with pytest.raises(ValueError, match="SpringString.mass"):
        SpringString(20, D, 1.0, -1.0)
