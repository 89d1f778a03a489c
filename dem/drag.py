"""Implicit linear drag on group-mean velocities (a pore fluid's response, linearised).

A fluid solved every few DEM steps hands the grains forces that depend on the grains' mean
velocity in each averaging volume (a group: an FE cell). Held constant over the DEM steps,
that dependence is an explicit drag, unstable once the held interval exceeds twice the
relaxation time m / alpha. Here the force's change since the fluid step is taken as a
linear drag on the group's mean velocity,

    f_i = -alpha_i (U_g - U_g^ref)            (i in group g, U_g = sum w_j v_j / sum w_j),

with U^ref the group means the fluid last saw, and integrated by backward Euler on the
half-step velocities of velocity Verlet (L-stable: no overshoot at any dt alpha / m, and
the terminal velocity under a steady force is exact). `dem.Simulation.step` applies it
(``drag=``, or a hook) after the force pass, before the second half-kick: it adds ``f`` to
the FREE rows' forces, which both half-kicks around the step's end then use.

Nothing here knows what the groups are: the coupling layer supplies plain arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dem.state import FREE

__all__ = ["GroupDrag", "group_means"]


@njit(cache=True)
def group_drag(v, force, g, dt, group, weight, wdt_m, alpha, axes, scale, shift, su, out,
               hit):
    """Backward-Euler group drag: ``out`` (n, 3) [N] the drag on every particle (0 where
    ``group < 0``), also added to ``force``. v (n, 3) half-step velocities [m/s]; force
    (n, 3) the forces of this pass [N]; g (3,) [m/s^2]; group (n,) int64 (-1: not dragged,
    e.g. not FREE); weight (n,) the mean's weights; wdt_m (n,) weight dt / mass [s/kg];
    alpha (n,) [N s/m]; axes (3,) 0/1 the components dragged; per group (G,), constant
    over the interval (`GroupDrag.arrays`): scale = 1 / (sum w (1 + lam)) and (G, 3) shift
    = u_ref / (1 + lam), lam = dt sum(w alpha / m) / sum w; su (G, 3) scratch; hit (n,)
    int8 the integrator's flags of the rows whose forces the kicks read: set for every
    dragged row (a grain out of contact would otherwise keep its drag in a row no kick
    reads, and carry it on)."""
    su[:] = 0.0
    for i in range(v.shape[0]):
        k = group[i]
        if k < 0:
            continue
        w = weight[i]
        a = wdt_m[i]
        for c in range(3):
            su[k, c] += w * (v[i, c] + dt * g[c]) + a * force[i, c]
    for k in range(su.shape[0]):
        for c in range(3):
            su[k, c] = axes[c] * (su[k, c] * scale[k] - shift[k, c])
    for i in range(v.shape[0]):
        k = group[i]
        if k < 0:
            for c in range(3):
                out[i, c] = 0.0
            continue
        for c in range(3):
            f = -alpha[i] * su[k, c]
            out[i, c] = f
            force[i, c] += f
        hit[i] = 1


def group_means(v: np.ndarray, group: np.ndarray, weight: np.ndarray, n_groups: int):
    """(G, 3) weighted means of v (n, 3) over the particles of each group (0 if empty)."""
    if len(group) and group.min() < 0:   # (the mask copies: only when some are left out)
        ok = group >= 0
        group, weight, v = group[ok], weight[ok], v[ok]
    sw = np.bincount(group, weight, minlength=n_groups)
    out = np.zeros((n_groups, 3))
    for c in range(3):
        s = np.bincount(group, weight * v[:, c], minlength=n_groups)
        out[:, c] = np.divide(s, sw, out=np.zeros_like(s), where=sw > 0)
    return out


class GroupDrag:
    """The implicit group drag of one interval between two fluid steps.

    Args:
        group: (n,) int group of every particle (-1: no drag).
        weight: (n,) > 0 weights of the group means (particle volumes [m^3]).
        alpha: (n,) >= 0 drag coefficients [N s/m].
        u_ref: (G, 3) reference group means [m/s].
        axes: (3,) flags of the velocity components dragged.

    Use: ``sim.step(n, drag=drag)`` (or ``hook=drag.hook(sim)``: the same bits, in the
    Python step loop).
    """

    def __init__(self, group, weight, alpha, u_ref, axes=(1, 1, 1)):
        self.group = np.ascontiguousarray(group, np.int64)
        n = len(self.group)
        self.weight = np.ascontiguousarray(weight, float)
        self.alpha = np.ascontiguousarray(alpha, float)
        self.u_ref = np.ascontiguousarray(u_ref, float).reshape(-1, 3)
        self.axes = np.asarray(axes, float).reshape(3)
        if self.weight.shape != (n,) or self.alpha.shape != (n,):
            raise ValueError(f"GroupDrag: weight and alpha must be ({n},)")
        if n and self.group.max() >= len(self.u_ref):
            raise ValueError(f"GroupDrag: group {self.group.max()} but only {len(self.u_ref)} "
                             f"reference means")
        if not (np.isfinite(self.alpha).all() and (self.alpha >= 0).all()):
            raise ValueError("GroupDrag: alpha must be finite and >= 0")
        self._su = np.zeros((len(self.u_ref), 3))
        self.force = np.zeros((n, 3))  #: the drag of the last step [N]
        self._for = None        # (dt, masses, kinds) the interval's constants were taken at
        self._consts = None

    def apply(self, sim) -> None:
        """Add the drag to the forces of ``sim`` now (in its step hook)."""
        p = sim.p
        group_drag(p.v, p.force, sim.gravity, sim.dt, *self.arrays(sim), sim.forced)

    def arrays(self, sim) -> tuple:
        """The kernel's arguments after (v, force, g, dt) (`dem.fused_steps`' loop too):
        group (-1 where not FREE), weight, weight dt / mass, alpha, axes, the groups' scale
        and shift (constant while dt, the masses and the kinds are), scratch, output."""
        p = sim.p
        seen = self._for
        if seen is None or seen[0] != sim.dt or not (np.array_equal(seen[1], p.mass)
                                                     and np.array_equal(seen[2], p.kind)):
            self._for = (sim.dt, p.mass.copy(), p.kind.copy())
            group = np.where(p.kind == FREE, self.group, -1)
            on = group >= 0
            G = len(self.u_ref)
            wdt_m = self.weight * sim.dt / p.mass
            sw = np.bincount(group[on], self.weight[on], minlength=G)
            sa = np.bincount(group[on], (wdt_m * self.alpha)[on], minlength=G)
            lam = np.divide(sa, sw, out=np.zeros(G), where=sw > 0)   # dt sum(w a/m) / sum w
            scale = np.divide(1.0, sw * (1.0 + lam), out=np.zeros(G), where=sw > 0)
            shift = self.u_ref / (1.0 + lam)[:, None]
            self._consts = (group, self.weight, wdt_m, self.alpha, self.axes, scale, shift)
        return (*self._consts, self._su, self.force)

    def hook(self, sim):
        """A `dem.Simulation.step` hook applying the drag every step (never ends the call)."""
        def _hook():
            self.apply(sim)
            return False
        return _hook
