"""Dynamic DE x FE coupling: implicit FE steps with explicit DE sub-steps (DESIGN main loop).

One FE step ``t_n -> t_n+1`` (generalized-alpha, :class:`granfe.dynamics.GeneralizedAlpha`)
iterates, from the saved particle state at ``t_n``:

1. ghost motion at ``t_n`` (converged) and at ``t_n+1`` (current FE iterate); inside the
   step the ghosts move linearly in time between the two (interpolated kinematics, so the DE
   never sees a jump);
2. the particles advance by explicit sub-steps over the interval;
3. their motion at ``t_n+1`` is projected onto the prescribed FE dofs (eq. 79-90);
4. the FE step is solved with those Dirichlet values;

with Aitken relaxation, until the prescribed values change less than ``tol``. The overlap
is a Schwarz overlap: each model keeps its own mass and stiffness there and they exchange
only kinematics, so no partition weights are needed for this scheme.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from coupling.interface import Aitken, ConstantRelaxation, CouplingInterface
from coupling.regions import CouplingRegions
from coupling.staggered import InterfaceDidNotConverge
from granfe.dynamics import GeneralizedAlpha

__all__ = ["DynamicOptions", "DynamicCoupling"]


@dataclass(frozen=True)
class DynamicOptions:
    """Interface iteration of a dynamic coupled step: tolerance, iterations, Aitken."""

    tol: float = 1e-8
    max_iterations: int = 50
    aitken: bool = True
    rho_inf: float = 1.0
    regularization: float = 0.0

    def __post_init__(self):
        if not 0 < self.tol < 1:
            raise ValueError(f"tol must lie in (0, 1), got {self.tol!r}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations!r}")


class DynamicCoupling:
    """Couples a micropolar FE problem (implicit) and :class:`dem.bonded.BondedDynamics`.

    Args:
        problem: the FE problem (create it, add its own conditions, then couple).
        dt: FE time step [s]; the particles sub-step inside it.
        x, kinds: coupled particles (n, 3) and their kinds (0 free, 1 ghost).
        particles: explicit particle dynamics whose ``ghosts`` are the kind-1 particles.
        regions: gives the prescribed FE nodes.
    """

    def __init__(self, problem, dt: float, x, kinds, particles, regions: CouplingRegions,
                 options: DynamicOptions = DynamicOptions()):
        self.interface = CouplingInterface(problem, x, kinds, regions, options.regularization)
        if not np.array_equal(np.sort(particles.ghosts), self.interface.ghost_index):
            raise ValueError("the particle dynamics' ghosts must be exactly the kind-1 particles")
        self.stepper = GeneralizedAlpha(problem, dt, rho_inf=options.rho_inf)
        self.problem, self.particles, self.options = problem, particles, options
        self.history: list[dict] = []
        self.timings = {"operators": self.interface.setup_time, "particles": 0.0, "fe": 0.0,
                        "projection": 0.0}
        self.substeps = 0

    @property
    def t(self) -> float:
        return self.stepper.t

    def _prescribed_from_w(self):
        w = self.problem.w.x.array
        return np.concatenate([w[f.prescribed] for f in self.interface.fields])

    def step(self) -> int:
        """One coupled FE step; returns the number of interface iterations."""
        iface, st, pd, opts = self.interface, self.stepper, self.particles, self.options
        dt = float(st.dt.value)
        saved = pd.save()
        g0 = pd.pack_ghosts(*iface.ghost_motion())
        st.predict()
        current = self._prescribed_from_w()
        aitken = Aitken(iface, 1.0) if opts.aitken else ConstantRelaxation(iface, 1.0)
        for it in range(1, opts.max_iterations + 1):  # noqa: B007 (the count is returned)
            t0 = time.perf_counter()
            pd.restore(saved)
            g1 = pd.pack_ghosts(*iface.ghost_motion())
            n_sub = pd.advance(dt, g0, g1)
            t1 = time.perf_counter()
            current, res = aitken.update(current, iface.project(*pd.motion()))
            t2 = time.perf_counter()
            iface.set_prescribed(current)
            st.solve()
            self.timings["particles"] += t1 - t0
            self.timings["projection"] += t2 - t1
            self.timings["fe"] += time.perf_counter() - t2
            if res < opts.tol:
                break
        else:
            raise InterfaceDidNotConverge(
                f"dynamic coupling at t = {st.t + dt:.4e} s: interface residual {res:.2e} after "
                f"{opts.max_iterations} iterations (tol {opts.tol:g}); reduce dt or widen the overlap")
        # the accepted DE state is the one advanced with the final ghost motion
        pd.restore(saved)
        pd.advance(dt, g0, pd.pack_ghosts(*iface.ghost_motion()))
        st.finish()
        self.substeps += n_sub
        self.history.append({"t": st.t, "iterations": it, "interface_residual": res})
        return it
