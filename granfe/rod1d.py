"""1D micropolar Timoshenko rod with axial stretch (seed 001 §2.2.2-2.2.4, eq. 8-57).

Kinematics (eq. 8): ``u_1 = u(x) - x_2 theta(x)``, ``u_2 = v(x)``, micro-rotation
``phi_3 = theta``. The reduced Galerkin form (eq. 39-40, with the element matrices
eq. 54-57) per unit length, with ``C = lam + 2 mu + kappa``:

* axial (test du):      ``du' C (A u' - Q theta')``
* transverse (test dv): ``dv' (mu + kappa) A (v' - theta)``
* rotation (test dth):  ``dth' [C (I theta' - Q u') + gamma A theta'] + dth kappa A (theta - v')``

The seed keeps only ``w_1,1 sigma_11 + w_2,1 sigma_12`` of the stress power (eq. 30) and
takes the skew stress ``sigma_12 - sigma_21 = kappa (v' - theta)`` in the angular balance,
so the rotation equation sees only ``kappa / (mu + kappa)`` of the shear force and
``K^{theta v} != (K^{v theta})^T`` (the seed says so under eq. 51). This is
``formulation="seed"`` (the default; it reproduces seed Fig. 4, ~3 cm tip deflection).
``formulation="energy"`` adds the omitted ``w_1,2 sigma_21`` term: the form is then the
derivative of the strain energy (symmetric, classical Timoshenko with shear stiffness
``(mu + kappa) A``), about 11x softer in bending for ``kappa = 0.1 mu``.

Spaces: u P1, v P2 (middle node), theta P1 on ``dolfinx.mesh.create_interval``
(``basix.ufl.mixed_element``), eq. 52-53. Stiffness scaling ``g = (g_u, g_v, g_theta)``
multiplies the rows of each balance equation (seed 001 §2.4.3: "which equation they
influence"). Solved with PETSc LU (MUMPS).
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)
from mpi4py import MPI
from petsc4py import PETSc

import basix.ufl
import dolfinx.fem.petsc
import numpy as np
import scipy.sparse as sp
import ufl
from dolfinx import default_scalar_type, fem, mesh

from granfe.materials import MicropolarMaterial

__all__ = ["Rod1D", "RodSolution", "cantilever_tip"]

FORMULATIONS = ("seed", "energy")


class RodSolution:
    """Nodal fields sorted by x on this rank (owned + ghost dofs).

    Attributes: ``x_u, u`` (n_u,), ``x_v, v`` (n_v,), ``x_theta, theta`` (n_theta,) [m, rad].
    """

    def __init__(self, rod: Rod1D, w: fem.Function):
        self.function = w
        for name, (dofs, x) in rod.field_dofs.items():
            setattr(self, f"x_{name}", x)
            setattr(self, name, w.x.array[dofs].copy())

    def at(self, x: float, comm: MPI.Comm) -> np.ndarray:
        """(u, v, theta) at abscissa ``x`` [m], identical on every rank (collective)."""
        vals = np.full(3, -np.inf)
        for k, name in enumerate(("u", "v", "theta")):
            xs, ys = getattr(self, f"x_{name}"), getattr(self, name)
            hit = np.flatnonzero(np.isclose(xs, x, atol=1e-12))
            if hit.size:
                vals[k] = ys[hit[0]]
        out = np.empty(3)
        comm.Allreduce(vals, out, op=MPI.MAX)
        return out


def cantilever_tip(material: MicropolarMaterial, length: float, area: float, inertia: float,
                   force: tuple[float, float], formulation: str = "seed") -> tuple[float, float]:
    """Closed-form tip (u, v) [m] of the Q = 0 cantilever loaded by ``force = (F_x, F_y)`` [N].

    ``u = F_x L / (C A)``; from the strong form of eq. 39-40 with ``theta' (tip) = 0`` and
    ``theta (clamp) = 0``: ``v = c F_y L^3 / (3 B) + F_y L / ((mu + kappa) A)`` with bending
    stiffness ``B = C I + gamma A`` and ``c = kappa / (mu + kappa)`` for the seed
    formulation, ``c = 1`` for the energy one.
    """
    m = material
    C = m.lam + 2 * m.mu + m.kappa
    B = C * inertia + m.gamma * area
    GA = (m.mu + m.kappa) * area
    c = m.kappa / (m.mu + m.kappa) if formulation == "seed" else 1.0
    return force[0] * length / (C * area), c * force[1] * length**3 / (3 * B) + force[1] * length / GA


class Rod1D:
    """Micropolar Timoshenko rod on [x0, x0 + length] (seed 001 §2.2).

    Args:
        material: micropolar moduli (lam, mu, kappa, gamma used).
        length: rod length L [m] (> 0).
        area: cross-section area A [m^2] (> 0).
        inertia: second moment of area I [m^4] (> 0).
        n_elements: number of elements (>= 1).
        comm: MPI communicator (the interval mesh is distributed by dolfinx).
        first_moment: Q [m^3] (0 for a symmetric section).
        formulation: "seed" (eq. 39-40 as printed) or "energy" (symmetric), see module doc.
        scaling: (g_u, g_v, g_theta) row scaling of the three balance equations (> 0).
        x0: left end abscissa [m].
    """

    def __init__(self, material: MicropolarMaterial, length: float, area: float, inertia: float,
                 n_elements: int, comm: MPI.Comm = MPI.COMM_WORLD, *, first_moment: float = 0.0,
                 formulation: str = "seed", scaling=(1.0, 1.0, 1.0), x0: float = 0.0):
        for name, val in (("length", length), ("area", area), ("inertia", inertia)):
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"Rod1D.{name} must be a finite positive number, got {val!r}")
        if int(n_elements) != n_elements or n_elements < 1:
            raise ValueError(f"Rod1D.n_elements must be an integer >= 1, got {n_elements!r}")
        if formulation not in FORMULATIONS:
            raise ValueError(f"Rod1D.formulation must be one of {FORMULATIONS}, got {formulation!r}")
        if len(scaling) != 3 or not all(np.isfinite(g) and g > 0 for g in scaling):
            raise ValueError(f"Rod1D.scaling must be three positive numbers, got {scaling!r}")
        self.material, self.length, self.x0 = material, float(length), float(x0)
        self.area, self.inertia, self.formulation = float(area), float(inertia), formulation
        self.comm = comm
        self.mesh = mesh.create_interval(comm, int(n_elements), [x0, x0 + length])
        el = basix.ufl.mixed_element([basix.ufl.element("Lagrange", "interval", k)
                                      for k in (1, 2, 1)])
        self.V = fem.functionspace(self.mesh, el)
        c = lambda v: fem.Constant(self.mesh, default_scalar_type(v))  # noqa: E731
        m = material
        self._C, self._GA = c(m.lam + 2 * m.mu + m.kappa), c((m.mu + m.kappa) * area)
        self._A, self._I, self._Q = c(area), c(inertia), c(first_moment)
        self._gam, self._kap, self._mu = c(m.gamma), c(m.kappa), c(m.mu)
        self.g = c(np.asarray(scaling, dtype=float))
        # per-cell row weights of the u, v, theta equations (energy factoring, seed eq. 119)
        self.W = fem.functionspace(self.mesh, ("DG", 0))
        self.cell_weights = [fem.Function(self.W, name=f"w_{f}") for f in ("u", "v", "theta")]
        for wk in self.cell_weights:
            wk.x.array[:] = 1.0
        self._w = fem.Function(self.V)
        self.a = fem.form(ufl.derivative(self.residual(self._w), self._w))
        self.field_dofs = self._field_dofs()

    def residual(self, w: fem.Function) -> ufl.Form:
        """The scaled residual form of eq. 39-40 (internal virtual work, no loads)."""
        u, v, th = ufl.split(w)
        du, dv, dth = ufl.TestFunctions(self.V)
        d = lambda f: f.dx(0)  # noqa: E731
        C, GA, A, I, Q = self._C, self._GA, self._A, self._I, self._Q
        wu, wv, wth = self.cell_weights
        gu, gv, gth = self.g[0] * wu, self.g[1] * wv, self.g[2] * wth
        gamma_shear = d(v) - th
        r_u = d(du) * C * (A * d(u) - Q * d(th))
        r_v = d(dv) * GA * gamma_shear
        r_th = d(dth) * (C * (I * d(th) - Q * d(u)) + self._gam * A * d(th))
        skew = self._kap * A if self.formulation == "seed" else GA
        r_th += -dth * skew * gamma_shear
        return (gu * r_u + gv * r_v + gth * r_th) * ufl.dx

    def _field_dofs(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per field: (parent dof indices, x [m]) sorted by x, owned and ghost."""
        out = {}
        for k, name in enumerate(("u", "v", "theta")):
            Vc, parent = self.V.sub(k).collapse()
            parent = parent[0] if isinstance(parent, list) else parent  # 0.11 returns a list
            x = Vc.tabulate_dof_coordinates()[:, 0]
            order = np.argsort(x)
            out[name] = (np.asarray(parent)[order], x[order])
        return out

    def end_dofs(self, end: str) -> np.ndarray:
        """Local parent dofs (u, v, theta) at the "left" or "right" end (may be empty)."""
        if end not in ("left", "right"):
            raise ValueError(f"end must be 'left' or 'right', got {end!r}")
        xe = self.x0 if end == "left" else self.x0 + self.length
        out = []
        for name in ("u", "v", "theta"):
            dofs, x = self.field_dofs[name]
            hit = np.flatnonzero(np.isclose(x, xe, atol=1e-12 * self.length))
            out.append(dofs[hit[0]] if hit.size else -1)
        return np.asarray(out, dtype=np.int32)

    def solve(self, end_loads=(0.0, 0.0, 0.0), clamp: str = "right") -> RodSolution:
        """Cantilever clamped at ``clamp`` with loads (F_x [N], F_y [N], M [N m]) at the other end.

        Collective. Assembles K with the clamp as Dirichlet rows, puts the end loads in
        the right-hand side on the owning rank and solves with MUMPS LU.
        """
        free = "left" if clamp == "right" else "right"
        clamp_dofs = self.end_dofs(clamp)
        bc = fem.dirichletbc(fem.Function(self.V), clamp_dofs[clamp_dofs >= 0])
        A = dolfinx.fem.petsc.assemble_matrix(self.a, bcs=[bc])
        A.assemble()
        w = fem.Function(self.V)
        b = w.x.petsc_vec.duplicate()
        b.set(0.0)
        n_owned = self.V.dofmap.index_map.size_local * self.V.dofmap.bs
        with b.localForm() as bl:
            for dof, load in zip(self.end_dofs(free), end_loads, strict=False):
                if 0 <= dof < n_owned:
                    bl.array[dof] += load
        b.assemble()
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOperators(A)
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        ksp.solve(b, w.x.petsc_vec)
        if ksp.getConvergedReason() <= 0:
            raise RuntimeError(f"Rod1D LU solve failed, KSP reason {ksp.getConvergedReason()}")
        w.x.scatter_forward()
        ksp.destroy(), A.destroy(), b.destroy()
        return RodSolution(self, w)

    def stiffness(self) -> sp.csr_matrix:
        """Unconstrained stiffness K (n_dofs, n_dofs) over the local dof numbering (serial only).

        Non-symmetric for ``formulation="seed"``; ``f_int(D) = K D`` (eq. 51).
        """
        if self.comm.size > 1:
            raise RuntimeError("Rod1D.stiffness gathers a serial scipy matrix: run on one rank")
        return self._to_scipy(self.a)

    def mass(self, weight=None) -> sp.csr_matrix:
        """Consistent mass (n_dofs, n_dofs) over the local dof numbering (serial), eq. 92/112.

        Kinetic energy density ``rho (A u'^2 + A v'^2 + (I + A j) theta'^2) / 2`` from the
        kinematics of eq. 8, with the material's ``rho`` and micro-inertia ``j``.
        ``weight``: a callable of the cell midpoint x [m] -> share, or a number: the
        continuum's share r of the kinetic energy of each cell (eq. 112-113).
        """
        if self.comm.size > 1:
            raise RuntimeError("Rod1D.mass gathers a serial scipy matrix: run on one rank")
        r = fem.Function(self.W)
        xm = self.W.tabulate_dof_coordinates()[:, 0]
        r.x.array[:] = 1.0 if weight is None else (weight(xm) if callable(weight) else weight)
        u, v, th = ufl.TrialFunctions(self.V)
        du, dv, dth = ufl.TestFunctions(self.V)
        A, rho = self._A, self.material.rho
        inertia = self._I + A * self.material.j
        form = r * rho * (A * u * du + A * v * dv + inertia * th * dth) * ufl.dx
        return self._to_scipy(fem.form(form))

    @staticmethod
    def _to_scipy(a: fem.Form) -> sp.csr_matrix:
        A = dolfinx.fem.petsc.assemble_matrix(a)
        A.assemble()
        indptr, indices, data = A.getValuesCSR()
        K = sp.csr_matrix((data, indices, indptr), shape=A.getSize())
        A.destroy()
        return K

    def set_cell_weights(self, field: str, weight) -> None:
        """Row weight of equation ``field`` ("u", "v", "theta") per cell: a callable of the
        cell midpoint x [m] -> weight, or a number. Clears the cached K."""
        k = ("u", "v", "theta").index(field)
        xm = self.W.tabulate_dof_coordinates()[:, 0]
        w = weight(xm) if callable(weight) else np.full(xm.size, float(weight))
        self.cell_weights[k].x.array[:] = w
        self.__dict__.pop("_K", None)

    @property
    def K(self) -> sp.csr_matrix:
        if not hasattr(self, "_K"):
            self._K = self.stiffness()
        return self._K

    def f_int(self, D: np.ndarray) -> np.ndarray:
        """Internal force vector ``K D`` (n_dofs,) [N, N m] for nodal values D (serial)."""
        return self.K @ D
