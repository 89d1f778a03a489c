"""Staggered (Schwarz-type) DE x FE coupling for quasi-static 2D/3D problems (DESIGN main loop).

One coupled solve iterates:

1. ghost particles follow the FE fields at their centroids: ``Q^ = N D`` (seed 001 eq. 74-78);
2. the particle subproblem is solved with the ghosts prescribed;
3. free-particle motion is projected onto the prescribed FE dofs of the overlap,
   ``D^ = M^-1 N^^T (Q - N_D D)`` (eq. 79-90);
4. the FE problem is solved (SNES) with ``D^`` as Dirichlet values;

until the relative change of ``D^`` and of the ghost motion falls below ``tol``. Aitken's
dynamic relaxation (Kuettler & Wall 2008) accelerates the fixed point on ``D^``. Each
iteration's interface residual is logged in :attr:`StaggeredCoupling.history`. A solve that
does not converge raises :class:`InterfaceDidNotConverge` after restoring the last
converged FE state.

The particle side is any object with ``solve(u_ghost, theta_ghost) -> (u, theta)`` for all
particles (``u`` (n, dim), ``theta`` (n,) in 2D or (n, 3) in 3D), e.g.
:class:`dem.bonded.BondedSubproblem`. It is replicated on every rank (identical inputs give
identical outputs), while the FE side and the operators are distributed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from coupling.interface import Aitken, CouplingInterface
from coupling.regions import CouplingRegions

__all__ = ["StaggeredOptions", "StaggeredCoupling", "InterfaceDidNotConverge", "ParticleSubproblem"]


class InterfaceDidNotConverge(RuntimeError):
    """The staggered iteration did not reach its tolerance; the message gives the history."""


class ParticleSubproblem(Protocol):
    """What the staggered loop needs of the particles: their motion for given ghost motion."""

    def solve(self, u_ghost: np.ndarray, theta_ghost: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class StaggeredOptions:
    """Tolerances of the staggered loop.

    Attributes:
        tol: relative change of the interface values (D^ and ghost motion) to stop.
        max_iterations: iterations before :class:`InterfaceDidNotConverge`.
        aitken: Aitken dynamic relaxation on D^ (else fixed relaxation ``omega``).
        omega: first (or fixed) relaxation factor in (0, 1].
        regularization: of the nodal projection (0: plain L2 projection).
    """

    tol: float = 1e-10
    max_iterations: int = 200
    aitken: bool = True
    omega: float = 1.0
    regularization: float = 0.0

    def __post_init__(self):
        if not (0 < self.tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {self.tol!r}")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {self.max_iterations!r}")
        if not (0 < self.omega <= 1):
            raise ValueError(f"omega must lie in (0, 1], got {self.omega!r}")


@dataclass
class StaggeredCoupling:
    """Couples a :class:`granfe.problem.MicropolarProblem` and a particle subproblem.

    Args:
        problem: the FE problem (its boundary conditions and loads stay in force).
        x: particle centroids (n, 3) [m], every particle of the subproblem, same on all ranks.
        kinds: (n,) 0 = free, 1 = ghost (from :meth:`CouplingRegions.particle_kinds`).
        particles: the particle subproblem (ghosts = particles with kind 1, in index order).
        regions: gives the prescribed FE nodes (B^h~).
        options: :class:`StaggeredOptions`.
    """

    problem: object
    x: np.ndarray
    kinds: np.ndarray
    particles: ParticleSubproblem
    regions: CouplingRegions
    options: StaggeredOptions = field(default_factory=StaggeredOptions)

    def __post_init__(self):
        self.interface = CouplingInterface(self.problem, self.x, self.kinds, self.regions,
                                           self.options.regularization)
        self.x, self.kinds = self.interface.x, self.interface.kinds
        self.comm, self.gdim = self.interface.comm, self.interface.gdim
        self.history: list[dict] = []
        self.timings = {"operators": self.interface.setup_time, "particles": 0.0, "fe": 0.0,
                        "projection": 0.0}

    def solve(self) -> int:
        """Iterate to a coupled equilibrium; returns the number of iterations."""
        opts, iface = self.options, self.interface
        state0 = self.problem.w.x.array.copy()
        current = iface.prescribed_values()
        aitken = Aitken(iface, opts.omega, opts.aitken)
        ghost_prev = None
        for it in range(1, opts.max_iterations + 1):
            t0 = time.perf_counter()
            u_g, th_g = iface.ghost_motion()
            self.u, self.theta = self.particles.solve(u_g, th_g)
            t1 = time.perf_counter()
            target = iface.project(self.u, self.theta)
            t2 = time.perf_counter()
            current, res = aitken.update(current, target)
            iface.set_prescribed(current)
            try:
                self.problem.solve()
            except Exception:
                self.problem.w.x.array[:] = state0
                raise
            t3 = time.perf_counter()
            g_all = np.concatenate([u_g.ravel(), np.ravel(th_g)])
            dg = (np.linalg.norm(g_all - ghost_prev) / max(np.linalg.norm(g_all), 1e-300)
                  if ghost_prev is not None else 1.0)
            ghost_prev = g_all
            self.history.append({"iteration": it, "interface_residual": res,
                                 "ghost_change": float(dg), "omega": aitken.omega})
            self.timings["particles"] += t1 - t0
            self.timings["projection"] += t2 - t1
            self.timings["fe"] += t3 - t2
            if res < opts.tol and dg < max(opts.tol, 1e-14) * 10:
                return it
            if not np.isfinite(res):
                break
        self.problem.w.x.array[:] = state0
        tail = ", ".join(f"{h['interface_residual']:.2e}" for h in self.history[-5:])
        raise InterfaceDidNotConverge(
            f"staggered DE x FE iteration did not converge in {it} iterations "
            f"(tol {opts.tol:g}); last interface residuals: {tail}. The FE state before this "
            f"solve was restored; try a wider overlap (handshake), more iterations or omega < 1"
        )
