"""Implicit dynamics of the micropolar continuum: generalized-alpha (Chung & Hulbert 1993).

Mass ``rho`` acts on u and rotary inertia ``rho j`` on phi. The spectral radius at
infinite frequency ``rho_inf`` in [0, 1] is the one damping parameter: ``rho_inf = 1``
gives alpha_m = alpha_f = 1/2, beta = 1/4, gamma = 1/2, the trapezoidal (Newmark
average acceleration) family, which conserves the energy of a linear elastic body
exactly; smaller values damp high frequencies with second-order accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

from granfe.forms import inertia_work, internal_work, kinetic_energy_density, strain, curvature, strain_energy_density
from granfe.problem import MicropolarProblem

__all__ = ["AlphaParameters", "GeneralizedAlpha"]


@dataclass(frozen=True)
class AlphaParameters:
    """Generalized-alpha parameters from the high-frequency spectral radius ``rho_inf``."""

    rho_inf: float = 1.0

    def __post_init__(self):
        if not (0.0 <= self.rho_inf <= 1.0):
            raise ValueError(f"rho_inf (spectral radius at infinite frequency) must lie in [0, 1], "
                             f"got {self.rho_inf!r}")

    @property
    def alpha_m(self) -> float:
        return (2 * self.rho_inf - 1) / (self.rho_inf + 1)

    @property
    def alpha_f(self) -> float:
        return self.rho_inf / (self.rho_inf + 1)

    @property
    def gamma(self) -> float:
        return 0.5 + self.alpha_f - self.alpha_m

    @property
    def beta(self) -> float:
        return 0.25 * (1 + self.alpha_f - self.alpha_m) ** 2


def _split(expr, gdim):
    u = ufl.as_vector([expr[i] for i in range(gdim)])
    phi = expr[gdim] if gdim == 2 else ufl.as_vector([expr[gdim + i] for i in range(3)])
    return u, phi


class GeneralizedAlpha:
    """Time stepper over a :class:`MicropolarProblem` (its BCs, loads and solver options).

    Loads given to the problem as ``fem.Constant`` are evaluated at ``t_{n+1-alpha_f}``:
    update them (``.value``) before each :meth:`step` with :meth:`load_time`.
    """

    def __init__(self, problem: MicropolarProblem, dt: float, rho_inf: float = 1.0,
                 prefix: str | None = None):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
        self.problem = problem
        self.params = p = AlphaParameters(rho_inf)
        self.t = 0.0
        self.dt = fem.Constant(problem.domain, float(dt))
        V = problem.V
        self.w_old = fem.Function(V, name="w_old")
        self.v = fem.Function(V, name="velocity")
        self.a = fem.Function(V, name="acceleration")
        w, c = problem.w, problem.constants
        dt_, b, g = self.dt, p.beta, p.gamma
        a_new = (w - self.w_old - dt_ * self.v) / (b * dt_**2) - (1 - 2 * b) / (2 * b) * self.a
        w_mid = (1 - p.alpha_f) * w + p.alpha_f * self.w_old
        a_mid = (1 - p.alpha_m) * a_new + p.alpha_m * self.a
        gdim = problem.gdim
        du, dphi = ufl.TestFunctions(V)
        u_m, phi_m = _split(w_mid, gdim)
        au, aphi = _split(a_mid, gdim)
        F = (inertia_work(au, aphi, du, dphi, c) + internal_work(u_m, phi_m, du, dphi, c)) * problem.dx
        L = problem.external_work(du, dphi)
        F = F - L if L != 0 else F
        options = {"snes_lag_jacobian": -2, "snes_lag_jacobian_persists": True}
        options.update(problem.petsc_options)
        saved, problem.petsc_options = problem.petsc_options, options
        self._snes = problem.snes_problem(F, prefix or problem.prefix + "dyn_")
        problem.petsc_options = saved
        vu, vphi = ufl.split(self.v)
        u, phi = ufl.split(w)
        self._kinetic = fem.form(kinetic_energy_density(vu, vphi, c) * problem.dx)
        self._elastic = fem.form(strain_energy_density(strain(u, phi), curvature(phi), c) * problem.dx)

    def load_time(self) -> float:
        """The time at which loads of the next step are evaluated, ``t_{n+1-alpha_f}``."""
        return self.t + (1 - self.params.alpha_f) * self.dt.value

    def step(self) -> int:
        """Advance one step; return SNES iterations (raises with the PETSc reason on failure)."""
        p, dt = self.params, float(self.dt.value)
        w = self.problem.w
        self.w_old.x.array[:] = w.x.array
        # predictor: constant acceleration (exact for the linear problem after one Newton step)
        w.x.array[:] += dt * self.v.x.array + 0.5 * dt**2 * self.a.x.array
        self._snes.solve()
        try:
            its = self.problem.checked(self._snes, f"dynamic step at t = {self.t + dt:.6g} s")
        except Exception:
            w.x.array[:] = self.w_old.x.array
            raise
        wn, wo, v, a = w.x.array, self.w_old.x.array, self.v.x.array, self.a.x.array
        a_new = (wn - wo - dt * v) / (p.beta * dt**2) - (1 - 2 * p.beta) / (2 * p.beta) * a
        v[:] = v + dt * ((1 - p.gamma) * a + p.gamma * a_new)
        a[:] = a_new
        self.t += dt
        return its

    def energies(self) -> tuple[float, float]:
        """(kinetic, elastic) energy of the current state [J] (per unit thickness in 2D)."""
        comm = self.problem.domain.comm
        k = comm.allreduce(fem.assemble_scalar(self._kinetic), MPI.SUM)
        e = comm.allreduce(fem.assemble_scalar(self._elastic), MPI.SUM)
        return k, e
