"""Periodic cell with a prescribed macroscopic velocity gradient (RVE tests, seed 004).

The cell is ``{origin + h s : s in [0, 1)^dim}`` with column vectors h (dim, dim) [m]; it
deforms as dh/dt = L h under the velocity gradient L [1/s] (homogeneous simple shear:
L = gamma_dot e_x (x) e_y, Lees-Edwards in the limit of a cell sheared with its contents).
Particle velocities ``v`` are *fluctuations* about the affine field L (x - origin): the
drift is x += dt (v + L (x - origin)), the contact relative velocity of i with the image
x_j + h k of j adds L d (d: branch vector), which includes the velocity jump L h k across
the faces. Fluctuations follow m dv/dt = F (the SLLOD streaming term -m L v is left out:
it matters at strain rates comparable to the fluctuation rates, not for quasi-static
RVEs), so the total fluctuation momentum is conserved exactly.

Particles are wrapped into the cell at every neighbour-list rebuild (in between they may
sit up to a skin outside it, seen through the same images); contact history is keyed by
the pair, so it survives wraps. In 2D (disks) x and y are periodic, z carries the unit
thickness. Use: ``Simulation(particles, material, cell=PeriodicCell(h0, L))``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PeriodicCell", "cell_stress"]


def _square(name, a, dim):
    a = np.asarray(a, float)
    if a.shape != (dim, dim) or not np.isfinite(a).all():
        raise ValueError(f"PeriodicCell.{name} must be a finite ({dim}, {dim}) array, got "
                         f"shape {a.shape}")
    out = np.zeros((3, 3))
    out[:dim, :dim] = a
    return out


class PeriodicCell:
    """A deforming periodic cell (state: ``h`` (3, 3) [m] now, ``velocity_gradient`` (3, 3)
    [1/s], which may be changed between steps, ``strain_time`` [s]).

    Args:
        h0: (dim, dim) column vectors of the cell [m] (dim 2 or 3; det > 0).
        velocity_gradient: (dim, dim) L [1/s] (default 0: a fixed periodic box).
        origin: (dim,) or (3,) corner of the cell [m].
    """

    def __init__(self, h0, velocity_gradient=None, origin=None):
        h0 = np.asarray(h0, float)
        if h0.ndim != 2 or h0.shape[0] not in (2, 3):
            raise ValueError(f"PeriodicCell.h0 must be (2, 2) or (3, 3), got shape {h0.shape}")
        self.dim = h0.shape[0]
        self.h = _square("h0", h0, self.dim)
        if self.dim == 2:
            self.h[2, 2] = 1.0  # unit thickness of the disks, not periodic
        if not np.linalg.det(self.h) > 0:
            raise ValueError("PeriodicCell.h0 must have a positive determinant (right-handed "
                             "cell vectors of non-zero volume)")
        lg = np.zeros((self.dim, self.dim)) if velocity_gradient is None else velocity_gradient
        self.velocity_gradient = _square("velocity_gradient", lg, self.dim)
        o = np.zeros(3) if origin is None else np.asarray(origin, float).ravel()
        if o.size not in (self.dim, 3) or not np.isfinite(o).all():
            raise ValueError(f"PeriodicCell.origin must be {self.dim} finite numbers")
        self.origin = np.zeros(3)
        self.origin[: o.size] = o
        self.h0 = self.h.copy()

    @property
    def volume(self) -> float:
        """Cell volume [m^3] (2D: area x unit thickness)."""
        return float(np.linalg.det(self.h))

    @property
    def deformation_gradient(self) -> np.ndarray:
        """F = h h0^-1 (3, 3) since the start."""
        return self.h @ np.linalg.inv(self.h0)

    def state_dict(self) -> dict:
        """Copies of h, h0, velocity_gradient and origin (3, 3) / (3,) and ``dim``."""
        return dict(h=self.h.copy(), h0=self.h0.copy(),
                    velocity_gradient=self.velocity_gradient.copy(), origin=self.origin.copy(),
                    dim=int(self.dim))

    def load_state(self, d) -> None:
        """Restore a `state_dict`; ValueError naming an entry that does not fit."""
        if int(d["dim"]) != self.dim:
            raise ValueError(f"state 'cell.dim' is {int(d['dim'])}, this cell {self.dim}")
        for k, shape in (("h", (3, 3)), ("h0", (3, 3)), ("velocity_gradient", (3, 3)),
                         ("origin", (3,))):
            a = np.array(d[k], float)
            if a.shape != shape:
                raise ValueError(f"state 'cell.{k}' has shape {a.shape}, not {shape}")
            setattr(self, k, a)

    def advance(self, dt: float):
        """H <- (I + dt L) h: the same affine map the drift applies to the particles."""
        self.h = self.h + dt * (self.velocity_gradient @ self.h)

    def wrap(self, x):
        """Move rows of x (n, 3) [m] into the cell by whole cell vectors (in place)."""
        s = (x - self.origin) @ np.linalg.inv(self.h).T
        k = np.floor(s)
        if self.dim == 2:
            k[:, 2] = 0.0
        moved = (k != 0).any(axis=1)
        if moved.any():
            x[moved] -= k[moved] @ self.h.T
        return x

    def as_kernel_args(self, img):
        """(flag, h, L, img) for `dem.forces.pair_forces`."""
        return (1, self.h, self.velocity_gradient, img)


def cell_stress(sim, symmetric: bool = True) -> np.ndarray:
    """Love-Weber stress (3, 3) [Pa] of a periodic simulation: 1/V sum_c b (x) f over the
    touching pairs with the branch vector b through the nearest image (`dem.stress`
    conventions: tension positive, f the force on i by j; 2D: per unit thickness)."""
    from dem.stress import love_weber_stress

    cell = sim.cell
    if cell is None:
        raise ValueError("cell_stress needs a Simulation with a PeriodicCell (sim.cell)")
    pairs, force, branch = sim.contact_forces(return_branch=True)
    # one point pair per contact: i at 0 and the image of j at b, so x[j] - x[i] = b
    m = len(pairs)
    x = np.zeros((2 * m, 3))
    x[1::2] = branch
    idx = np.arange(2 * m).reshape(m, 2)
    return love_weber_stress(x, idx, force, cell.volume, symmetric=symmetric)
