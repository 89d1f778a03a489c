"""Bonded (glued) particle assemblies with linear bonds, solved quasi-statically.

A bond between touching particles i and j carries a normal spring k_n, a tangential
spring k_t at the contact point and a rotational spring k_r (Potyondy & Cundall 2004
parallel bond without breakage, small displacements). The relative displacement at the
contact point is ``delta = u_j + theta_j x c_j - u_i - theta_i x c_i`` with
``c_i = r_i n``, ``c_j = -r_j n``; the bond energy is
``(k_n delta_n^2 + k_t |delta_t|^2 + k_r |theta_j - theta_i|^2) / 2``. The stiffness is
assembled once as a sparse matrix (dofs per particle: 2D ``(u_x, u_y, theta_z)``, 3D
``(u, theta)``), so a quasi-static solve with prescribed (ghost) particles is one sparse
factorisation. This is the linear DE model of the coupling patch tests and the coupled
versus full-DEM comparisons; the Hertz-Mindlin glued string of seed 001 is ``dem.glued``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

__all__ = ["BondedAssembly", "BondedDynamics", "BondedSubproblem", "find_bonds", "hexagonal_lattice",
           "hexagonal_lattice_constants", "hexagonal_lattice_micropolar"]


def hexagonal_lattice(lower, upper, radius: float) -> np.ndarray:
    """Centres (n, 3) of touching disks of ``radius`` on a hexagonal lattice inside a 2D box."""
    if not radius > 0:
        raise ValueError(f"radius must be > 0 m, got {radius!r}")
    d = 2 * radius
    (x0, y0), (x1, y1) = np.asarray(lower, float)[:2], np.asarray(upper, float)[:2]
    rows = np.arange(y0 + radius, y1 - radius + 1e-12 * d, d * np.sqrt(3) / 2)
    pts = []
    for k, y in enumerate(rows):
        xs = np.arange(x0 + radius + (k % 2) * radius, x1 - radius + 1e-12 * d, d)
        pts.append(np.column_stack([xs, np.full_like(xs, y), np.zeros_like(xs)]))
    return np.vstack(pts) if pts else np.zeros((0, 3))


def hexagonal_lattice_constants(kn: float, kt: float) -> tuple[float, float]:
    """Plane Lame constants (lam, mu) [Pa m = N/m per unit thickness... see note] of a
    hexagonal lattice of equal disks with bonds (kn, kt) [N/m] to its 6 neighbours.

    Affine strain with zero particle rotation: ``lam = sqrt(3)/4 (kn - kt)``,
    ``mu = sqrt(3)/4 (kn + kt)`` (per unit thickness; summing the bond energies over the
    three bond directions of a cell of area sqrt(3)/2 d^2).
    """
    s = np.sqrt(3) / 4
    return s * (kn - kt), s * (kn + kt)


def hexagonal_lattice_micropolar(kn: float, kt: float, kr: float) -> dict[str, float]:
    """Micropolar (Eringen) constants of the bonded hexagonal lattice, per unit thickness.

    Matching the bond energy with the continuum energy for a linear field (u, phi = theta):
    the relative displacement at a contact is ``d eps n`` with ``eps = grad u + e . phi``,
    so ``lam = sqrt(3)/4 (kn - kt)``, ``2 mu + kappa = sqrt(3)/2 (kn + kt)``,
    ``kappa = sqrt(3) kt`` and ``gamma = sqrt(3) kr`` (Eringen's ``mu`` is then
    ``sqrt(3)/4 (kn - kt)``; the classical shear modulus is ``mu + kappa / 2``).
    """
    s = np.sqrt(3) / 4
    return {"lam": s * (kn - kt), "mu": s * (kn - kt), "kappa": 4 * s * kt, "gamma": 4 * s * kr}


def find_bonds(x: np.ndarray, radius: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """Pairs (m, 2), i < j, of particles whose gap is below ``tolerance`` times the mean radius."""
    x = np.asarray(x, float)
    radius = np.broadcast_to(np.asarray(radius, float), (len(x),))
    tree = cKDTree(x)
    pairs = tree.query_pairs(2 * radius.max() * (1 + tolerance), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    gap = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1) - radius[pairs].sum(axis=1)
    return pairs[gap <= tolerance * radius.mean()].astype(np.int64)


def _cross_matrix(c):
    """(m, 3, 3) matrices S with S @ theta = theta x c."""
    S = np.zeros((len(c), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = c[:, 2], -c[:, 1]
    S[:, 1, 0], S[:, 1, 2] = -c[:, 2], c[:, 0]
    S[:, 2, 0], S[:, 2, 1] = c[:, 1], -c[:, 0]
    return S


@dataclass
class BondedAssembly:
    """Particles (x, radius) with linear bonds; ``dim`` 2 (disks) or 3 (spheres).

    Attributes:
        x: centres (n, 3) [m]; radius: (n,) [m]; bonds: (m, 2) pairs.
        kn, kt, kr: bond stiffnesses [N/m, N/m, N m/rad].
    """

    x: np.ndarray
    radius: np.ndarray
    bonds: np.ndarray
    kn: float
    kt: float
    kr: float = 0.0
    dim: int = 2

    def __post_init__(self):
        self.x = np.asarray(self.x, float)
        self.radius = np.broadcast_to(np.asarray(self.radius, float), (len(self.x),)).copy()
        if self.x.ndim != 2 or self.x.shape[1] != 3:
            raise ValueError(f"x must have shape (n, 3), got {self.x.shape}")
        if not np.all(np.isfinite(self.x)):
            bad = np.flatnonzero(~np.isfinite(self.x).all(1))[:5].tolist()
            raise ValueError(f"x has non-finite entries at particles {bad}")
        if np.any(self.radius <= 0):
            raise ValueError(f"radius must be > 0; particle {int(np.argmin(self.radius))} has "
                             f"{self.radius.min()!r}")
        for name in ("kn", "kt", "kr"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite stiffness >= 0, got {getattr(self, name)!r}")
        if not self.kn > 0:
            raise ValueError(f"kn must be > 0, got {self.kn!r}")
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim!r}")
        self.bonds = np.asarray(self.bonds, dtype=np.int64).reshape(-1, 2)
        self.K = self._stiffness()

    @property
    def dofs_per_particle(self) -> int:
        return 3 if self.dim == 2 else 6

    def _bond_matrices(self):
        """B (m, 3, 12) mapping [u_i, th_i, u_j, th_j] (3D layout) to delta; normals (m, 3)."""
        i, j = self.bonds.T
        d = self.x[j] - self.x[i]
        n = d / np.linalg.norm(d, axis=1)[:, None]
        I = np.broadcast_to(np.eye(3), (len(n), 3, 3))
        B = np.concatenate([-I, -_cross_matrix(self.radius[i, None] * n), I,
                            _cross_matrix(-self.radius[j, None] * n)], axis=2)
        return B, n

    def _stiffness(self) -> sp.csr_matrix:
        m = len(self.bonds)
        ndof = self.dofs_per_particle
        B, n = self._bond_matrices()
        P = np.einsum("mi,mj->mij", n, n)
        D = self.kn * P + self.kt * (np.eye(3) - P)
        Kb = np.einsum("mki,mkl,mlj->mij", B, D, B)
        R = np.zeros((m, 3, 12))
        R[:, :, 3:6], R[:, :, 9:12] = -np.eye(3), np.eye(3)
        Kb += self.kr * np.einsum("mki,mkj->mij", R, R)
        if self.dim == 2:  # keep (u_x, u_y, theta_z)
            keep = np.array([0, 1, 5, 6, 7, 11])
            Kb = Kb[:, keep][:, :, keep]
        i, j = self.bonds.T
        local = np.arange(ndof)
        dofs = np.concatenate([i[:, None] * ndof + local, j[:, None] * ndof + local], axis=1)
        rows = np.repeat(dofs, 2 * ndof, axis=1).ravel()
        cols = np.tile(dofs, (1, 2 * ndof)).ravel()
        N = len(self.x) * ndof
        return sp.csr_matrix((Kb.ravel(), (rows, cols)), shape=(N, N))

    def pack(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Dof vector from displacements (n, dim) and rotations (n,) in 2D or (n, 3) in 3D."""
        q = np.empty((len(self.x), self.dofs_per_particle))
        q[:, : self.dim] = u[:, : self.dim]
        q[:, self.dim:] = np.reshape(theta, (len(self.x), -1))
        return q.ravel()

    def unpack(self, q: np.ndarray):
        q = q.reshape(len(self.x), self.dofs_per_particle)
        return q[:, : self.dim].copy(), (q[:, 2].copy() if self.dim == 2 else q[:, 3:].copy())

    def energy(self, q: np.ndarray) -> float:
        """Elastic energy of the bonds [J] (per unit thickness in 2D)."""
        return 0.5 * float(q @ (self.K @ q))

    def forces(self, q: np.ndarray):
        """Bond forces (n, dim) and moments on the particles for dof vector q (= -K q)."""
        return self.unpack(-(self.K @ q))


class BondedSubproblem:
    """Quasi-static solve of a :class:`BondedAssembly` with prescribed particles.

    ``K_ff q_f = f_ext,f - K_fp q_p`` factorised once (SuperLU). The prescribed particles
    are the ``ghosts`` (values given to :meth:`solve`, e.g. by the coupling) followed by
    ``fixed`` ones whose values live in :attr:`fixed_u` / :attr:`fixed_theta` (supports,
    a rigid punch; change them between solves to load the assembly).
    """

    def __init__(self, assembly: BondedAssembly, ghosts: np.ndarray, fixed: np.ndarray | None = None):
        self.assembly = a = assembly
        ghosts = np.asarray(ghosts, dtype=np.int64)
        fixed = np.zeros(0, dtype=np.int64) if fixed is None else np.asarray(fixed, dtype=np.int64)
        if np.intersect1d(ghosts, fixed).size:
            raise ValueError("a particle cannot be both a ghost and fixed")
        self.n_ghost = len(ghosts)
        self.fixed = fixed
        self.fixed_u = np.zeros((len(fixed), a.dim))
        self.fixed_theta = np.zeros(len(fixed)) if a.dim == 2 else np.zeros((len(fixed), 3))
        prescribed = np.concatenate([ghosts, fixed])
        ndof = a.dofs_per_particle
        is_p = np.zeros(len(a.x), bool)
        is_p[prescribed] = True
        self.prescribed = prescribed
        self.free = np.flatnonzero(~is_p)
        self._dof_p = (prescribed[:, None] * ndof + np.arange(ndof)).ravel()
        self._dof_f = (self.free[:, None] * ndof + np.arange(ndof)).ravel()
        K = a.K.tocsc()
        self._Kfp = K[self._dof_f][:, self._dof_p]
        Kff = K[self._dof_f][:, self._dof_f]
        try:
            self._lu = spla.splu(Kff.tocsc())
        except RuntimeError as err:
            raise ValueError("the bonded assembly is not held: some free particles form a "
                             "mechanism (no bond path to a prescribed particle)") from err
        self.f_ext = np.zeros(len(a.x) * ndof)

    def solve(self, u_ghost: np.ndarray, theta_ghost: np.ndarray):
        """Displacements (n, dim) and rotations of all particles for given ghost motion."""
        a = self.assembly
        u_p = np.concatenate([np.reshape(u_ghost, (self.n_ghost, np.shape(u_ghost)[-1]))[:, : a.dim],
                              self.fixed_u])
        nr = 1 if a.dim == 2 else 3
        theta_p = np.concatenate([np.reshape(theta_ghost, (self.n_ghost, nr)),
                                  np.reshape(self.fixed_theta, (len(self.fixed), nr))])
        ndof = a.dofs_per_particle
        qp = np.empty((len(self.prescribed), ndof))
        qp[:, : a.dim] = u_p[:, : a.dim]
        qp[:, a.dim:] = np.reshape(theta_p, (len(self.prescribed), -1))
        qp = qp.ravel()
        qf = self._lu.solve(self.f_ext[self._dof_f] - self._Kfp @ qp)
        q = np.empty(len(a.x) * ndof)
        q[self._dof_p], q[self._dof_f] = qp, qf
        self.q = q
        return a.unpack(q)


class BondedDynamics:
    """Explicit dynamics of a :class:`BondedAssembly` (velocity Verlet, lumped masses).

    ``M qdd = f_ext - K q - c M qd`` for the free particles; the ghost particles follow a
    motion given at the two ends of an interval (linear in time, as the coupling prescribes
    from two FE states) and fixed particles keep their values. Masses per unit thickness in
    2D: ``m = rho pi r^2``, ``I = m r^2 / 2``; spheres in 3D: ``m = 4/3 rho pi r^3``,
    ``I = 2/5 m r^2``. The stable step is ``2 / omega_max`` of ``M^-1 K`` (Lanczos estimate);
    sub-steps use ``safety`` times it.
    """

    def __init__(self, assembly: BondedAssembly, density: float, ghosts: np.ndarray,
                 fixed: np.ndarray | None = None, damping: float = 0.0, safety: float = 0.5):
        if not (np.isfinite(density) and density > 0):
            raise ValueError(f"density must be > 0 kg/m^3, got {density!r}")
        if not (0 < safety <= 1):
            raise ValueError(f"safety must lie in (0, 1], got {safety!r}")
        self.assembly = a = assembly
        self.density, self.damping, self.safety = density, damping, safety
        r = a.radius
        if a.dim == 2:
            m = density * np.pi * r**2
            inertia = 0.5 * m * r**2
        else:
            m = 4.0 / 3.0 * density * np.pi * r**3
            inertia = 0.4 * m * r**2
        ndof = a.dofs_per_particle
        per = np.empty((len(r), ndof))
        per[:, : a.dim] = m[:, None]
        per[:, a.dim:] = inertia[:, None]
        self.mass = per.ravel()
        self.ghosts = np.asarray(ghosts, dtype=np.int64)
        self.fixed = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, dtype=np.int64)
        dof = lambda idx: (idx[:, None] * ndof + np.arange(ndof)).ravel()  # noqa: E731
        self._dof_g = dof(self.ghosts)
        moving = np.ones(len(r), bool)
        moving[self.ghosts] = moving[self.fixed] = False
        self._dof_f = dof(np.flatnonzero(moving))
        self.q = np.zeros(len(r) * ndof)
        self.v = np.zeros_like(self.q)
        self.f_ext = np.zeros_like(self.q)
        self.t = 0.0
        self.dt_critical = self._critical_step()
        self._acc = self._acceleration()

    def _critical_step(self) -> float:
        s = 1.0 / np.sqrt(self.mass)
        A = sp.diags(s) @ self.assembly.K @ sp.diags(s)
        lam = spla.eigsh(A.tocsc(), k=1, which="LA", return_eigenvectors=False, tol=1e-3)[0]
        return 2.0 / np.sqrt(lam)

    def _acceleration(self) -> np.ndarray:
        acc = np.zeros_like(self.q)
        f = self.f_ext - self.assembly.K @ self.q - self.damping * self.mass * self.v
        acc[self._dof_f] = f[self._dof_f] / self.mass[self._dof_f]
        return acc

    def save(self):
        return self.q.copy(), self.v.copy(), self._acc.copy(), self.t

    def restore(self, state) -> None:
        q, v, acc, t = state
        self.q[:], self.v[:], self._acc[:] = q, v, acc
        self.t = t

    def pack_ghosts(self, u_ghost, theta_ghost) -> np.ndarray:
        a = self.assembly
        n = len(self.ghosts)
        qg = np.empty((n, a.dofs_per_particle))
        qg[:, : a.dim] = np.reshape(u_ghost, (n, -1))[:, : a.dim]
        qg[:, a.dim:] = np.reshape(theta_ghost, (n, -1))
        return qg.ravel()

    def advance(self, interval: float, ghost_start: np.ndarray, ghost_end: np.ndarray,
                dt: float | None = None) -> int:
        """Advance by ``interval`` with ghost dofs moving linearly from ``ghost_start`` to
        ``ghost_end`` (packed with :meth:`pack_ghosts`); returns the number of sub-steps."""
        dt_max = self.safety * self.dt_critical
        if dt is not None and dt > self.dt_critical:
            raise ValueError(f"dt = {dt:.3e} s exceeds the critical step {self.dt_critical:.3e} s")
        n = max(1, int(np.ceil(interval / (dt or dt_max) - 1e-12)))
        h = interval / n
        g_vel = (ghost_end - ghost_start) / interval
        f, g = self._dof_f, self._dof_g
        for k in range(1, n + 1):
            self.v[f] += 0.5 * h * self._acc[f]
            self.q[f] += h * self.v[f]
            self.q[g] = ghost_start + (k / n) * (ghost_end - ghost_start)
            self.v[g] = g_vel
            self._acc = self._acceleration()
            self.v[f] += 0.5 * h * self._acc[f]
        self.t += interval
        if not np.all(np.isfinite(self.q)):
            raise FloatingPointError(f"bonded dynamics blew up at t = {self.t:.4e} s (NaN)")
        return n

    def motion(self):
        """(u (n, dim), theta) of all particles."""
        return self.assembly.unpack(self.q)

    def energies(self, particles: np.ndarray | None = None) -> tuple[float, float]:
        """(kinetic, elastic) energy [J]; with ``particles`` only their kinetic energy and the
        bonds with both ends among them."""
        a = self.assembly
        if particles is None:
            return 0.5 * float(self.v @ (self.mass * self.v)), a.energy(self.q)
        ndof = a.dofs_per_particle
        dofs = (np.asarray(particles)[:, None] * ndof + np.arange(ndof)).ravel()
        kin = 0.5 * float(self.v[dofs] @ (self.mass[dofs] * self.v[dofs]))
        mask = np.zeros(len(a.x), bool)
        mask[particles] = True
        inner = mask[a.bonds].all(axis=1)
        sub = BondedAssembly.__new__(BondedAssembly)
        sub.__dict__.update(a.__dict__)
        sub.bonds = a.bonds[inner]
        return kin, 0.5 * float(self.q @ (sub._stiffness() @ self.q))
