"""Implicit linear drag on group-mean velocities (a pore fluid's response, linearised).

A fluid solved every few DEM steps hands the grains forces that depend on the grains' mean
velocity in each averaging volume (a group: an FE cell). Held constant over the DEM steps,
that dependence is an explicit drag, unstable once the held interval exceeds twice the
relaxation time m / alpha. Here the force's change since the fluid step is taken as a
linear drag on the group's mean velocity,

    f_i = -alpha_i (U_g - U_g^ref)            (i in group g, U_g = sum w_j v_j / sum w_j),

with U^ref the group means the fluid last saw, and integrated by backward Euler on the
half-step velocities of velocity Verlet (L-stable: no overshoot at any dt alpha / m, and
the terminal velocity under a steady force is exact). The drag is applied by the hook of
`dem.Simulation.step` (after the force pass, before the second half-kick: it adds ``f`` to
the FREE rows' forces, which both half-kicks around the step's end then use).

Nothing here knows what the groups are: the coupling layer supplies plain arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dem.state import FREE

__all__ = ["GroupDrag", "group_means"]


@njit(cache=True)
def _group_drag(v, force, mass, kind, g, dt, group, weight, alpha, axes, u_ref, sw, sa, su,
                out, hit):
    """Backward-Euler group drag: ``out`` (n, 3) [N] the drag on every particle (0 where
    ``group < 0`` or not FREE), also added to ``force``. v (n, 3) half-step velocities
    [m/s]; force (n, 3) the forces of this pass [N]; g (3,) [m/s^2]; group (n,) int64;
    weight (n,) the mean's weights; alpha (n,) [N s/m]; axes (3,) 0/1 the components
    dragged; u_ref (G, 3); sw, sa (G,) and su (G, 3) scratch; hit (n,) int8 the integrator's
    flags of the rows whose forces the kicks read: set for every dragged row (a grain out
    of contact would otherwise keep its drag in a row no kick reads, and carry it on)."""
    sw[:] = 0.0
    sa[:] = 0.0
    su[:] = 0.0
    for i in range(v.shape[0]):
        k = group[i]
        if k < 0 or kind[i] != FREE:
            continue
        w = weight[i]
        sw[k] += w
        sa[k] += w * alpha[i] / mass[i]
        for c in range(3):
            su[k, c] += w * (v[i, c] + dt * (force[i, c] / mass[i] + g[c]))
    for k in range(sw.shape[0]):
        if sw[k] > 0.0:
            lam = dt * sa[k] / sw[k]
            for c in range(3):
                su[k, c] = axes[c] * (su[k, c] / sw[k] - u_ref[k, c]) / (1.0 + lam)
    for i in range(v.shape[0]):
        k = group[i]
        for c in range(3):
            out[i, c] = 0.0
        if k < 0 or kind[i] != FREE:
            continue
        for c in range(3):
            f = -alpha[i] * su[k, c]
            out[i, c] = f
            force[i, c] += f
        hit[i] = 1


def group_means(v: np.ndarray, group: np.ndarray, weight: np.ndarray, n_groups: int):
    """(G, 3) weighted means of v (n, 3) over the particles of each group (0 if empty)."""
    ok = group >= 0
    sw = np.bincount(group[ok], weight[ok], minlength=n_groups)
    out = np.zeros((n_groups, 3))
    for c in range(3):
        s = np.bincount(group[ok], weight[ok] * v[ok, c], minlength=n_groups)
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

    Use: ``sim.step(n, hook=drag.hook(sim))``.
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
        G = len(self.u_ref)
        self._sw, self._sa, self._su = np.zeros(G), np.zeros(G), np.zeros((G, 3))
        self.force = np.zeros((n, 3))  #: the drag of the last step [N]

    def apply(self, sim) -> None:
        """Add the drag to the forces of ``sim`` now (in its step hook)."""
        p = sim.p
        _group_drag(p.v, p.force, p.mass, p.kind, sim.gravity, sim.dt, self.group,
                    self.weight, self.alpha, self.axes, self.u_ref, self._sw, self._sa,
                    self._su, self.force, sim.forced)

    def hook(self, sim):
        """A `dem.Simulation.step` hook applying the drag every step (never ends the call)."""
        def _hook():
            self.apply(sim)
            return False
        return _hook
