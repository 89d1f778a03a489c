"""The grains' kinematics as a micromorphic continuum sees them: the micro-deformation at the
prescribed FE nodes from the grains' displacements, and the ghosts' rotation from the
continuum's micro-deformation. The one place the coupling knows a micromorphic model
(:func:`micro_deformation`: a field ``phi`` of shape (gdim, gdim), ``phi = chi - I``).

**Prescribed nodes** (the kinematic counterpart of seed 002's stresses, which average the
grains' forces and their first moment over a domain): at a node a with position x_a the
micro-deformation is the weighted least-squares affine fit of the free grains' displacements
in the node's support, weighted by the node's shape function at the grains' reference
positions X_p::

    min over (u_a, phi_a) of  sum_p N_a(X_p) |u_p - u_a - phi_a (X_p - x_a)|^2

whose minimiser is, with weights w_p = N_a(X_p), W = sum w_p, the weighted mean offset
xbar = sum w_p (X_p - x_a) / W and the weighted second moment J = sum w_p (X_p - x_a - xbar)
(X_p - x_a - xbar)^T (gdim x gdim)::

    phi_a = sum_p w_p u_p (X_p - x_a - xbar)^T J^-1.

It reproduces an affine field u = u0 + H X exactly (phi_a = H) for any grains with a
non-singular J: the micro-element deforms with the grains about it (micro follows macro,
Eringen's relative deformation ``grad u - phi`` vanishing for a homogeneous deformation).
The intercept u_a is not used: the nodes' displacement is the L2 projection of
:class:`coupling.operators.NodalProjection`, as for the micropolar continuum.

Minimum support, no regularisation: the fit is refused (:class:`ThinSupport`, naming how many
nodes fail and where) for a node with fewer than ``min_grains`` grains of ``N_a > 0`` (default
``2 (gdim + 1)``, twice the unknowns of one row of the fit) or whose weighted spread is too
flat, ``lambda_min(J) / lambda_max(J) < min_spread`` (default 0.05: the grains spread in the
thinnest direction at least 0.22 times as far as in the widest). A regularised J would bias
phi toward zero where the support is thin; the coupling interface drops weakly supported
nodes first (``min_support``). The weights need ``N_a >= 0``: phi of degree 1.

**Ghosts**: a rigid sphere at x_g cannot follow the micro-deformation ``u + (chi - I) xi``
of the points xi of its micro-element: it carries its centroid's displacement u(x_g) and the
rotation part of ``(chi - I)``, the axial vector of ``skew(phi(x_g))``::

    theta_k = -e_kij skew(phi)_ij / 2,  i.e. 2D: theta_z = (phi_yx - phi_xy) / 2,
    3D: theta = ((phi_zy - phi_yz), (phi_xz - phi_zx), (phi_yx - phi_xy)) / 2,

which for a rigid rotation ``phi = W``, ``W v = theta x v``, is theta itself; the stretch
(the symmetric part of phi) is not carried by the sphere.

Parallel: each rank sums over the grains in its cells into its local (owned and ghost) dofs,
the sums are added into the owners (one reverse scatter) and every owner fits its nodes.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)

import dolfinx.la
import numpy as np

__all__ = ["MicroDeformationFit", "ThinSupport", "axial_vector", "micro_deformation"]


class ThinSupport(ValueError):
    """Prescribed nodes whose grains cannot fix a micro-deformation (too few or too flat)."""


def micro_deformation(problem) -> bool:
    """True if the model's field ``phi`` is a (gdim, gdim) micro-deformation ``chi - I``
    (the micromorphic models), False if it is a micropolar rotation; the dispatch of the
    coupling interface."""
    gdim = problem.domain.geometry.dim
    shapes = {f.name: tuple(f.shape) for f in problem.fields}
    return shapes.get("phi") == (gdim, gdim)


def axial_vector(phi: np.ndarray, gdim: int) -> np.ndarray:
    """The rotation carried by a rigid grain: the axial vector of ``skew(phi)`` for rows of
    flat micro-deformations ``phi`` (n, gdim^2), row-major (``phi[:, gdim * i + j] =
    phi_ij``); (n,) theta_z in 2D, (n, 3) in 3D (module docstring)."""
    p = np.asarray(phi, dtype=float).reshape(-1, gdim, gdim)
    if gdim == 2:
        return 0.5 * (p[:, 1, 0] - p[:, 0, 1])
    return 0.5 * np.stack([p[:, 2, 1] - p[:, 1, 2], p[:, 0, 2] - p[:, 2, 0], p[:, 1, 0] - p[:, 0, 1]],
                          axis=1)


class MicroDeformationFit:
    """The least-squares micro-deformation of the module docstring at the prescribed dofs of
    the field ``phi``.

    Args:
        basis: the phi field's :class:`coupling.operators.FieldBasis` at this rank's free
            grains (the rows ``p * gdim^2 + k`` hold N_a(X_p) of component k = gdim i + j).
        points: (n, gdim) this rank's free grains' reference positions X_p [m], the basis's
            points in its order.
        prescribed: owned local parent dofs of phi to fit (every component of a node).
        min_grains: fewest grains with N_a > 0 a node's fit accepts (default 2 (gdim + 1)).
        min_spread: least lambda_min(J) / lambda_max(J) accepted, in (0, 1].

    Collective (construction, :meth:`update`, :meth:`fit`). Raises :class:`ThinSupport`.
    """

    def __init__(self, basis, points: np.ndarray, prescribed: np.ndarray, *,
                 min_grains: int | None = None, min_spread: float = 0.05):
        gdim = basis.V.mesh.geometry.dim
        if basis.value_size != gdim * gdim:
            raise ValueError(f"the basis has {basis.value_size} components per grain: not a "
                             f"(gdim, gdim) = ({gdim}, {gdim}) micro-deformation")
        degree = basis.V.sub(basis.sub).ufl_element().embedded_superdegree
        if degree != 1:
            raise ValueError(f"the micro-deformation fit weighs grains by N_a >= 0: phi of degree 1, "
                             f"got degree {degree}")
        self.min_grains = 2 * (gdim + 1) if min_grains is None else min_grains
        if not (isinstance(self.min_grains, int | np.integer) and self.min_grains >= gdim + 1):
            raise ValueError(f"min_grains must be an integer >= gdim + 1 = {gdim + 1} (the unknowns of "
                             f"one row of the affine fit), got {min_grains!r}")
        if not (np.isfinite(min_spread) and 0 < min_spread <= 1):
            raise ValueError(f"min_spread (lambda_min / lambda_max of the grains' second moment) must "
                             f"lie in (0, 1], got {min_spread!r}")
        self.min_spread = float(min_spread)
        self.gdim = gdim
        self.prescribed = np.sort(np.asarray(prescribed, dtype=np.int64))
        V = basis.V
        self._imap, self._bs = V.dofmap.index_map, V.dofmap.index_map_bs
        self.comm = V.mesh.comm
        self.update(basis, points)

    # ---- the grains' weights and moments ------------------------------------------------
    def _entries(self, basis, points):
        """Per non-zero of N: (grain, parent dof, weight, offset X_p - x_a (gdim,), row i)."""
        local = basis.local.tocoo()
        rows, cols, w = local.row, local.col.astype(np.int64), local.data
        keep = w > 0.0
        rows, cols, w = rows[keep], cols[keep], w[keep]
        k = self.gdim * self.gdim
        grain, comp = rows // k, rows % k
        node_x = basis.dof_coordinates[np.searchsorted(basis.dofs, cols), : self.gdim]
        xi = np.asarray(points, dtype=float).reshape(-1, self.gdim)[grain] - node_x
        return grain, cols, w, xi, comp // self.gdim, comp % self.gdim

    def _sum_to_owners(self, cols, values: np.ndarray) -> np.ndarray:
        """Per owned prescribed dof, the sums over every rank's grains of ``values`` (m, q)."""
        q = values.shape[1]
        vec = dolfinx.la.vector(self._imap, self._bs * q)
        acc = vec.array.reshape(-1, q)
        for c in range(q):
            acc[:, c] = np.bincount(cols, values[:, c], minlength=acc.shape[0])
        vec.scatter_reverse(dolfinx.la.InsertMode.add)
        return vec.array.reshape(-1, q)[self.prescribed].copy()

    def update(self, basis, points: np.ndarray) -> None:
        """Weights and second moments anew for grains at ``points`` (n, gdim) with ``basis``
        (after the grains moved); checks every node's support. Collective."""
        d = self.gdim
        grain, cols, w, xi, self._row, self._col = self._entries(basis, points)
        self._grain, self._cols = grain, cols
        # the component k of a dof rides along as a sum (count times k): its grains may lie
        # in another rank's cells
        moments = np.column_stack([w, np.ones_like(w), self._row * d + self._col, w[:, None] * xi,
                                   (w[:, None, None] * xi[:, :, None] * xi[:, None, :]).reshape(-1, d * d)])
        s = self._sum_to_owners(cols, moments)
        W, count, Sx, Sxx = s[:, 0], s[:, 1], s[:, 3: 3 + d], s[:, 3 + d:].reshape(-1, d, d)
        safe = np.where(W > 0, W, 1.0)
        xbar = Sx / safe[:, None]
        J = Sxx - np.einsum("n,ni,nj->nij", safe, xbar, xbar)
        J[W <= 0] = np.eye(d)
        lam = np.linalg.eigvalsh(J)
        spread = np.where(W > 0, lam[:, 0] / np.maximum(lam[:, -1], 1e-300), 0.0)
        self._check(basis, count, spread)
        self.grains_per_node = count
        self.spread = spread
        Jinv = np.linalg.inv(J)
        # phi_il of a dof = sum_m (S_ui,m - S_ui xbar_m) Jinv_ml: the column l of J^-1 per dof
        comp = np.rint(s[:, 2] / np.maximum(count, 1)).astype(np.int64)
        self._a = Jinv[np.arange(len(comp)), :, comp % d]        # (n_dofs, d)
        self._b = -np.einsum("nm,nm->n", xbar, self._a)          # coefficient of S_ui
        self._w, self._xi = w, xi

    def _check(self, basis, count, spread) -> None:
        bad = np.flatnonzero((count < self.min_grains) | (spread < self.min_spread))
        coords = basis.dof_coordinates[np.searchsorted(basis.dofs, self.prescribed[bad]), : self.gdim]
        nodes, first = np.unique(np.round(coords, 12), axis=0, return_index=True)
        found = self.comm.allgather([(tuple(c), int(count[bad[i]]), float(spread[bad[i]]))
                                     for c, i in zip(nodes[:3], first[:3], strict=False)])
        n_bad = self.comm.allreduce(len(nodes))
        if n_bad:
            n_all = self.comm.allreduce(len(np.unique(np.round(
                basis.dof_coordinates[np.searchsorted(basis.dofs, self.prescribed), : self.gdim], 12), axis=0)))
            where = "; ".join(f"node at {np.array2string(np.array(c), precision=4)}: {k} grain(s), "
                              f"spread {s:.3g}" for part in found for c, k, s in part)
            raise ThinSupport(
                f"{n_bad} of {n_all} prescribed node(s) have too thin a support for the micro-deformation "
                f"fit (it needs >= {self.min_grains} grains with N_a > 0 and a spread lambda_min / "
                f"lambda_max of their second moment >= {self.min_spread:g}): {where}. Drop such nodes "
                f"(a larger min_support of the interface, a smaller prescribed region) or add grains")

    # ---- the fit ------------------------------------------------------------------------
    def fit(self, u: np.ndarray) -> np.ndarray:
        """The fitted phi at the prescribed dofs (len(prescribed),) from this rank's free grains'
        displacements ``u`` (n, gdim) [m] (the basis's grains, in its order). Collective."""
        u = np.asarray(u, dtype=float).reshape(-1, self.gdim)
        wu = self._w * u[self._grain, self._row]
        s = self._sum_to_owners(self._cols, np.column_stack([wu, wu[:, None] * self._xi]))
        return self._b * s[:, 0] + np.einsum("nm,nm->n", s[:, 1:], self._a)
