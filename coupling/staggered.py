"""Staggered (Schwarz-type) DE x FE coupling for quasi-static 2D/3D problems (DESIGN main loop).

One coupled solve iterates:

1. ghost particles follow the FE fields at their centroids: ``Q^ = N D`` (seed 001 eq. 74-78);
2. the particle subproblem is solved with the ghosts prescribed;
3. free-particle motion is projected onto the prescribed FE dofs of the overlap,
   ``D^ = M^-1 N^^T (Q - N_D D)`` (eq. 79-90);
4. the FE problem is solved (SNES) with ``D^`` as Dirichlet values;

until the relative interface residual ``|H(D^) - D^| / |H(D^)|`` of the fixed point ``D^ =
H(D^)`` (steps 1-3 after an FE solve with ``D^``) falls below ``tol``. Before the first
iteration the FE problem is solved with the current ``D^`` (the FE predictor), so that every
pair ``(D^, H(D^))`` the accelerator sees is a sample of the map: a secant method must not learn
from an FE state that belongs to other prescribed values or loads. The accelerator is chosen
by name (:data:`ACCELERATORS`): constant relaxation, Aitken's dynamic relaxation (Kuettler &
Wall 2008) or the interface quasi-Newton method IQN-ILS (Degroote et al. 2009), which also
converges where plain iteration diverges. It lives as long as the coupling, and
:meth:`StaggeredCoupling.solve` starts a new step of it, so IQN-ILS can reuse the secant pairs
of earlier load steps (``IQNOptions.reuse``). Each iteration's interface residual is logged in
:attr:`StaggeredCoupling.history`. A solve that does not converge raises
:class:`InterfaceDidNotConverge` after restoring the FE state and prescribed values it started from.

The particle side is any object with ``solve(u_ghost, theta_ghost) -> (u, theta)`` for all
particles (``u`` (n, dim), ``theta`` (n,) in 2D or (n, 3) in 3D), e.g.
:class:`dem.bonded.BondedSubproblem`. It is replicated on every rank (identical inputs give
identical outputs), while the FE side and the operators are distributed.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from coupling.interface import IQNILS, Aitken, ConstantRelaxation, CouplingInterface, IQNOptions
from coupling.regions import CouplingRegions

__all__ = ["StaggeredOptions", "StaggeredCoupling", "InterfaceDidNotConverge", "ParticleSubproblem",
           "ACCELERATORS", "make_accelerator", "Accelerator"]


class InterfaceDidNotConverge(RuntimeError):
    """The staggered iteration did not reach its tolerance; the message gives the history."""


class ParticleSubproblem(Protocol):
    """What the staggered loop needs of the particles: their motion for given ghost motion."""

    def solve(self, u_ghost: np.ndarray, theta_ghost: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class Accelerator(Protocol):
    """What the staggered loop needs of an accelerator of the fixed point on ``D^``."""

    omega: float
    columns: int

    def update(self, current: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]: ...

    def new_step(self) -> None: ...

    def reset(self) -> None: ...


# name -> accelerator on the interface's space; the one table to extend
ACCELERATORS = {
    "constant": lambda space, opts: ConstantRelaxation(space, opts.omega),
    "aitken": lambda space, opts: Aitken(space, opts.omega),
    "iqn-ils": lambda space, opts: IQNILS(space, opts.omega, opts.iqn),
}


def make_accelerator(space, options: StaggeredOptions) -> Accelerator:
    """The accelerator ``options.accelerator`` on ``space`` (``dot`` / ``norm`` of the
    distributed interface vector, e.g. a :class:`CouplingInterface`)."""
    return ACCELERATORS[options.accelerator](space, options)


@dataclass(frozen=True)
class StaggeredOptions:
    """Tolerances of the staggered loop.

    Attributes:
        tol: relative interface residual ``|H(D^) - D^| / |H(D^)|`` to stop.
        max_iterations: iterations (particle solves) before :class:`InterfaceDidNotConverge`.
        accelerator: of the fixed point on D^, a name in :data:`ACCELERATORS`: ``"constant"``
            (relaxation ``omega``), ``"aitken"`` (dynamic relaxation from ``omega``) or
            ``"iqn-ils"`` (interface quasi-Newton; ``omega`` relaxes its first iteration).
        omega: first (or fixed) relaxation factor in (0, 1].
        iqn: :class:`coupling.interface.IQNOptions` of ``"iqn-ils"`` (pairs reused across
            load steps, most pairs, QR2 filter).
        regularization: of the nodal projection (0: plain L2 projection).
        aitken: deprecated, use ``accelerator``: True is ``"aitken"``, False ``"constant"``.
    """

    tol: float = 1e-10
    max_iterations: int = 200
    accelerator: str = "aitken"
    omega: float = 1.0
    iqn: IQNOptions = IQNOptions()
    regularization: float = 0.0
    aitken: bool | None = None

    def __post_init__(self):
        if not (0 < self.tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {self.tol!r}")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {self.max_iterations!r}")
        if not (0 < self.omega <= 1):
            raise ValueError(f"omega must lie in (0, 1], got {self.omega!r}")
        if self.aitken is not None:
            named = "aitken" if self.aitken else "constant"
            if self.accelerator not in ("aitken", named):
                raise ValueError(f"aitken = {self.aitken} contradicts accelerator = {self.accelerator!r}; "
                                 f"give accelerator only (aitken is deprecated)")
            warnings.warn(f"StaggeredOptions(aitken={self.aitken}) is deprecated: use "
                          f"accelerator={named!r}", DeprecationWarning, stacklevel=3)
            object.__setattr__(self, "accelerator", named)
            object.__setattr__(self, "aitken", None)
        if self.accelerator not in ACCELERATORS:
            raise ValueError(f"accelerator must be one of {sorted(ACCELERATORS)}, got {self.accelerator!r}")
        if not isinstance(self.iqn, IQNOptions):
            raise ValueError(f"iqn must be an IQNOptions, got {type(self.iqn).__name__}")


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
        self.accelerator = make_accelerator(self.interface, self.options)
        self.history: list[dict] = []
        self.timings = {"operators": self.interface.setup_time, "particles": 0.0, "fe": 0.0,
                        "projection": 0.0}

    def solve(self) -> int:
        """Iterate to a coupled equilibrium; returns the number of iterations (particle solves).

        On return the FE state is the solve with the last prescribed values ``D^`` and the
        particles' motion (:attr:`u`, :attr:`theta`) the answer to its ghost motion, with
        ``|H(D^) - D^| < tol |H(D^)|``."""
        opts, iface, acc = self.options, self.interface, self.accelerator
        start = (self.problem.w.x.array.copy(), iface.prescribed_values())
        current = start[1]
        acc.new_step()
        self._solve_fe(current, start)
        ghost_prev = None
        for it in range(1, opts.max_iterations + 1):
            t0 = time.perf_counter()
            u_g, th_g = iface.ghost_motion()
            self.u, self.theta = self.particles.solve(u_g, th_g)
            t1 = time.perf_counter()
            target = iface.project(self.u, self.theta)
            t2 = time.perf_counter()
            new, res = acc.update(current, target)
            g_all = np.concatenate([u_g.ravel(), np.ravel(th_g)])
            dg = (np.linalg.norm(g_all - ghost_prev) / max(np.linalg.norm(g_all), 1e-300)
                  if ghost_prev is not None else 1.0)
            ghost_prev = g_all
            self.history.append({"iteration": it, "interface_residual": res, "ghost_change": float(dg),
                                 "omega": acc.omega, "columns": acc.columns})
            self.timings["particles"] += t1 - t0
            self.timings["projection"] += t2 - t1
            if res < opts.tol:
                return it
            if not np.isfinite(res):
                break
            current = new
            self._solve_fe(current, start)
        self._restore(start)
        tail = ", ".join(f"{h['interface_residual']:.2e}" for h in self.history[-5:])
        raise InterfaceDidNotConverge(
            f"staggered DE x FE iteration ({opts.accelerator}) did not converge in {it} iterations "
            f"(tol {opts.tol:g}); last interface residuals: {tail}. The FE state and prescribed "
            f"values before this solve were restored; try accelerator='iqn-ils', a wider overlap "
            f"(handshake), more iterations or omega < 1"
        )

    def _solve_fe(self, prescribed: np.ndarray, start: tuple[np.ndarray, np.ndarray]) -> None:
        """The FE solve with the prescribed values; a failure restores ``start`` (FE state,
        prescribed values) and raises."""
        t0 = time.perf_counter()
        self.interface.set_prescribed(prescribed)
        try:
            self.problem.solve()
        except Exception:
            self._restore(start)
            raise
        self.timings["fe"] += time.perf_counter() - t0

    def _restore(self, start: tuple[np.ndarray, np.ndarray]) -> None:
        self.problem.w.x.array[:] = start[0]
        self.interface.set_prescribed(start[1])
