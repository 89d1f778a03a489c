"""Consolidation: backward-Euler time stepping of a Biot model, and the closed forms it is
verified against (Terzaghi's 1D consolidation, Mandel's problem).

A Biot model (:mod:`granfe.models.poroelastic`) is quasi-static in u with a transient
pressure: a time step is one static solve of a :class:`~granfe.problem.ContinuumProblem`
with the step's ``dt`` in a constant, committing the fluid content as the model's
quadrature-point history. So the problem's conditions, loads, reactions, checkpoints and
output serve unchanged; this module only adds the clock, fluid fluxes (scaled by ``dt``)
and a rigid platen carrying a prescribed force (Mandel's plates).

Typical use::

    problem = ContinuumProblem(mesh, Poroelastic(material), facet_tags=ft, tag_names=names)
    problem.fix("bottom", "u"); problem.fix("top", "p")        # drained top
    problem.traction("top", (0.0, -q))
    run = Consolidation(problem)
    run.undrained()                                             # t = 0+: instantaneous load
    for dt in steps: run.step(dt)
"""

from __future__ import annotations

import functools
import math

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
from dolfinx import default_scalar_type, fem
from scipy.optimize import brentq

from granfe.problem import ContinuumProblem

__all__ = ["Consolidation", "time_grid", "terzaghi_pressure", "terzaghi_settlement",
           "mandel_roots", "mandel_pressure", "mandel_top_displacement"]


class Consolidation:
    """Backward-Euler time stepping of a :class:`ContinuumProblem` of a Biot model.

    Loads and conditions held in ``fem.Constant`` act at the end of each step (set them
    before :meth:`step`). :attr:`t` is the time reached [s].
    """

    def __init__(self, problem: ContinuumProblem):
        if not hasattr(problem.model, "set_time_step"):
            raise TypeError(f"Consolidation steps a Biot model (granfe.models.poroelastic), "
                            f"got the {problem.model.name} model")
        self.problem = problem
        self.model = problem.model
        self.t = 0.0
        self._dropped: list = []     # pressure conditions left out of an undrained solve
        self._monitored: dict = {}
        #: name -> fluid volume rate entering in the last step (:meth:`monitor_inflow`)
        self.inflows: dict[str, float] = {}

    def flux(self, where, value: float = 0.0) -> fem.Constant:
        """Prescribed fluid inflow [m/s] (volume per unit area and time, into the body) on a
        boundary; returns the constant holding it (update ``.value`` between steps)."""
        holder = fem.Constant(self.problem.domain, default_scalar_type(value))
        self.problem.surface_load(where, "p", self.model.constants.dt * holder)
        return holder

    def _pressure_conditions(self) -> list:
        """The problem's Dirichlet conditions on the pore pressure."""
        ip = len(self.problem.fields) - 1
        return [bc for bc in self.problem.bcs + self._dropped
                if list(bc.function_space.component()) == [ip]]

    def _solve(self, dt: float, commit: bool = True) -> int:
        """One solve at step ``dt``; at ``dt = 0`` without the pressure conditions: in an
        instant no fluid flows anywhere, so the pressure is the undrained one up to a drained
        face too (the face drains during the first step of finite length). Keeping them
        would drain the elements along the face at once (measured: Mandel's centre
        pressure 0.8 % high at t = 0+ on a 16 x 16 mesh)."""
        self.model.set_time_step(dt)
        pressure = self._pressure_conditions() if dt == 0 else []
        if pressure != self._dropped:
            self.problem.bcs = [bc for bc in self.problem.bcs + self._dropped
                                if not any(bc is q for q in pressure)]
            self._dropped = pressure
            self.problem.invalidate()
        its = self.problem.solve(commit=False)
        if commit:
            self._commit(dt)
        return its

    def undrained(self) -> int:
        """The instantaneous (undrained) response to the current loads: a step of length 0,
        no fluid flows, prescribed pressures are not imposed (:meth:`_solve`). The time does
        not advance."""
        return self._solve(0.0)

    def step(self, dt: float) -> int:
        """Advance by ``dt`` > 0 [s] (one backward-Euler step)."""
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
        its = self._solve(dt)
        self.t += dt
        return its

    def monitor_inflow(self, name: str, where) -> None:
        """Record, at every step, the fluid volume rate [m^3/s, m^2/s in 2D] entering through
        a boundary with a prescribed pressure, in :attr:`inflows` ``[name]``: the residual of
        the mass balance at the boundary's pressure dofs over ``dt``, evaluated before the
        fluid content is committed. It conserves mass exactly: the inflows of all boundaries
        times ``dt`` sum to the change of the fluid content."""
        self._monitored[name] = where
        self.inflows[name] = 0.0

    def _commit(self, dt: float) -> None:
        if dt > 0:
            for name, where in self._monitored.items():
                self.inflows[name] = self.problem.reaction(where, "p") / dt
        self.problem.state.commit()

    def step_with_resultant(self, dt: float, control: fem.Constant, where, component: str,
                            force: float) -> float:
        """A step (``dt = 0``: the undrained response) in which the Dirichlet value
        ``control`` (from :meth:`ContinuumProblem.fix`, e.g. the settlement of a rigid
        platen) is chosen so that the reaction on ``where`` conjugate to ``component`` equals
        ``force`` [N, N/m in 2D]. The step is affine in the value: the solutions at two
        trial values, combined so that the reaction is ``force``, are the answer. Returns the
        value found."""
        if dt != 0 and not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
        problem = self.problem
        d0 = float(control.value)
        x = problem.domain.geometry.x
        size = problem.domain.comm.allreduce(float(np.ptp(x, axis=0).max()) if len(x) else 0.0,
                                             op=MPI.MAX)
        h = abs(d0) if d0 != 0 else 1e-6 * size
        solutions, reactions = [], []
        for d in (d0, d0 + h):
            control.value = d
            self._solve(dt, commit=False)
            solutions.append(problem.w.x.array.copy())
            reactions.append(problem.reaction(where, component))
        if reactions[1] == reactions[0]:
            raise ValueError(f"the reaction on {where!r} does not depend on the value of the "
                             f"condition given as control")
        theta = (force - reactions[0]) / (reactions[1] - reactions[0])
        control.value = d0 + theta * h
        problem.w.x.array[:] = (1 - theta) * solutions[0] + theta * solutions[1]
        problem.last_good[:] = problem.w.x.array
        self._commit(dt)
        self.t += dt
        return float(control.value)


def time_grid(t_end: float, n: int, power: float = 2.0, include=()) -> np.ndarray:
    """Times ``t_end (k / n)^power``, k = 1..n, merged with the times ``include`` (outputs):
    steps that grow with time, as consolidation slows down (``power = 2``: steps growing
    linearly from ``t_end / n^2``, the backward-Euler error spread evenly over a decay)."""
    if not (t_end > 0 and n >= 1 and power >= 1):
        raise ValueError(f"need t_end > 0, n >= 1, power >= 1; got {t_end}, {n}, {power}")
    t = t_end * (np.arange(1, n + 1) / n) ** power
    extra = np.asarray(include, dtype=float)
    if np.any((extra <= 0) | (extra > t_end)):
        raise ValueError(f"output times must lie in (0, t_end = {t_end}], got {extra.tolist()}")
    t = np.union1d(t, extra)
    # drop grid times closer than 1e-9 t_end to an included one (no zero-length steps)
    keep = np.ones(len(t), dtype=bool)
    for x in extra:
        near = np.isclose(t, x, rtol=0, atol=1e-9 * t_end) & (t != x)
        keep &= ~near
    return t[keep]


# ---- Terzaghi: a layer of height H, drained at z = 0, impermeable at z = H, uniaxial strain --
def terzaghi_pressure(z, t: float, *, H: float, p0: float, c: float, terms: int = 400):
    """Pore pressure [Pa] at distance ``z`` [m] from the drained face at time ``t`` > 0 [s]
    after a load that raised it to ``p0`` (Terzaghi 1925; Wang 2000, ch. 6):
    ``p = p0 sum_m 4/((2m+1) pi) sin((2m+1) pi z / 2H) exp(-(2m+1)^2 pi^2 c t / 4H^2)``."""
    z = np.asarray(z, dtype=float)
    m = 2 * np.arange(terms) + 1
    decay = np.exp(-(m * np.pi) ** 2 * c * t / (4 * H**2))
    return p0 * np.sum(4 / (m * np.pi) * np.sin(np.multiply.outer(z, m) * np.pi / (2 * H)) * decay,
                       axis=-1)


def terzaghi_settlement(t: float, *, H: float, q: float, material, terms: int = 400) -> float:
    """Settlement [m] (positive down) of the loaded face under a load ``q`` [Pa] applied at
    t = 0: ``s = (q H - alpha H p_mean) / (lam + 2 mu)``, from the undrained
    ``q H / (lam + 2 mu + alpha^2 M)`` to the drained ``q H / (lam + 2 mu)``."""
    m = 2 * np.arange(terms) + 1
    c, E_oed, alpha = material.c_oedometric, material.oedometric_modulus, material.fluid.alpha
    p0 = terzaghi_p0(q, material)
    mean = p0 * np.sum(8 / (m * np.pi) ** 2 * np.exp(-(m * np.pi) ** 2 * c * t / (4 * H**2)))
    return (q - alpha * mean) * H / E_oed


def terzaghi_p0(q: float, material) -> float:
    """Undrained pore pressure under a uniaxial-strain load q [Pa]:
    ``alpha q / (alpha^2 + (lam + 2 mu) / M)``."""
    f = material.fluid
    return f.alpha * q / (f.alpha**2 + material.oedometric_modulus * f.inv_M)


# ---- Mandel: plane strain, -a < x < a, -b < y < b between rigid frictionless plates -----------
@functools.lru_cache(maxsize=16)
def mandel_roots(nu: float, nu_u: float, n: int) -> np.ndarray:
    """The first ``n`` positive roots of ``tan(x) = (1 - nu) / (nu_u - nu) x``; the k-th lies
    in ``((k-1) pi, (k-1) pi + pi/2)``."""
    C = (1 - nu) / (nu_u - nu)
    f = lambda x: math.sin(x) - C * x * math.cos(x)  # noqa: E731
    eps = 1e-12
    return np.array([brentq(f, k * math.pi + eps, k * math.pi + math.pi / 2 - eps) if k else
                     brentq(f, eps, math.pi / 2 - eps) for k in range(n)])


def mandel_pressure(x, t: float, *, a: float, F: float, material, terms: int = 400):
    """Pore pressure [Pa] at ``x`` in Mandel's problem, plates pressed by a force ``2F``
    [N/m] on the width ``2a`` (the quarter model carries F) applied at t = 0 (Abousleiman et
    al. 1996; Cheng & Detournay 1988):
    ``p = 2 F B (1 + nu_u) / (3a) sum_n sin a_n / (a_n - sin a_n cos a_n)
    (cos(a_n x / a) - cos a_n) exp(-a_n^2 c t / a^2)``."""
    m = material
    r = mandel_roots(m.nu, m.nu_u, terms)
    x = np.asarray(x, dtype=float)
    coef = np.sin(r) / (r - np.sin(r) * np.cos(r)) * np.exp(-r**2 * m.c_mandel * t / a**2)
    series = np.sum(coef * (np.cos(np.multiply.outer(x, r) / a) - np.cos(r)), axis=-1)
    return 2 * F * m.B * (1 + m.nu_u) / (3 * a) * series


def mandel_top_displacement(t: float, *, a: float, b: float, F: float, material, terms: int = 400):
    """Vertical displacement [m] of the top plate at ``y = b`` (negative: compression):
    ``u_y = b F / (G a) [-(1 - nu) / 2 + (1 - nu_u) sum_n sin a_n cos a_n /
    (a_n - sin a_n cos a_n) exp(-a_n^2 c t / a^2)]`` (Abousleiman et al. 1996)."""
    m = material
    G = m.G
    r = mandel_roots(m.nu, m.nu_u, terms)
    s = np.sum(np.sin(r) * np.cos(r) / (r - np.sin(r) * np.cos(r)) * np.exp(-r**2 * m.c_mandel * t / a**2))
    return b * F / (G * a) * (-(1 - m.nu) / 2 + (1 - m.nu_u) * s)
