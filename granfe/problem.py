"""Static micropolar boundary-value problem: boundary conditions, loads, SNES solve.

Typical use (2D plane strain, mesh with named physical groups from gmsh)::

    problem = MicropolarProblem(mesh, material, facet_tags=ft, tag_names={"left": 1, ...})
    problem.fix("left", "u_x"); problem.fix("left", "phi")
    problem.traction("right", (1e6, 0.0))
    problem.solve()

Boundaries are named physical groups, integer tags, or a locator ``x -> bool mask``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem, mesh as _mesh
from mpi4py import MPI

from granfe.forms import MaterialConstants, internal_work, stresses
from granfe.materials import MicropolarMaterial
from granfe.solvers import (ITERATIVE, check_converged, check_ksp_converged, make_snes_problem,
                            rigid_body_modes)
from granfe.spaces import COMPONENTS, micropolar_space, sub_space

__all__ = ["MicropolarProblem", "MissingBoundary"]

Where = str | int | Callable[[np.ndarray], np.ndarray]


class MissingBoundary(ValueError):
    """A boundary named in a condition is not in the mesh's facet tags."""


class MicropolarProblem:
    """Quasi-static linear micropolar elasticity on a 2D (plane strain) or 3D mesh.

    Args:
        domain: the mesh (2D in the plane or 3D).
        material: the micropolar constants.
        facet_tags: boundary tags (e.g. from ``dolfinx.io.gmsh.model_to_mesh``).
        tag_names: physical-group names -> facet tag values.
        degree: Lagrange degrees of (u, phi).
        petsc_options: overrides of :data:`granfe.solvers.DIRECT`; ``solver="iterative"``
            starts from :data:`granfe.solvers.ITERATIVE` instead and attaches the
            rigid-body near-nullspace.
        prefix: unique PETSc options prefix.
        checkpoint_dir: where the last converged state is written if a solve fails.
    """

    def __init__(self, domain: _mesh.Mesh, material: MicropolarMaterial, *,
                 facet_tags: _mesh.MeshTags | None = None, tag_names: dict[str, int] | None = None,
                 degree: tuple[int, int] = (2, 1), solver: str = "direct",
                 petsc_options: dict | None = None, prefix: str = "granfe_",
                 checkpoint_dir: str | Path | None = None):
        if not isinstance(material, MicropolarMaterial):
            raise TypeError(f"material must be a MicropolarMaterial, got {type(material).__name__}")
        if solver not in ("direct", "iterative"):
            raise ValueError(f"solver must be 'direct' or 'iterative', got {solver!r}")
        self.domain = domain
        self.gdim = domain.geometry.dim
        self.material = material
        self.constants = MaterialConstants.from_material(domain, material)
        self.V = micropolar_space(domain, *degree)
        self.degree = degree
        self.w = fem.Function(self.V, name="w")
        self.facet_tags = facet_tags
        self.tag_names = dict(tag_names or {})
        self.solver_kind = solver
        self.petsc_options = dict(ITERATIVE if solver == "iterative" else {})
        self.petsc_options.update(petsc_options or {})
        self.prefix = prefix
        self.checkpoint_dir = None if checkpoint_dir is None else Path(checkpoint_dir)
        self.bcs: list[fem.DirichletBC] = []
        self._surface: list[tuple[np.ndarray, str, object]] = []
        self._volume: list[tuple[str, object]] = []
        self._snes = None
        self._last_good = self.w.x.array.copy()
        self.dx = ufl.Measure("dx", domain=domain)

    # ---- where ------------------------------------------------------------------------
    def facets(self, where: Where) -> np.ndarray:
        """Local boundary facet indices of a named group, a tag value, or a locator."""
        fdim = self.domain.topology.dim - 1
        if callable(where):
            return _mesh.locate_entities_boundary(self.domain, fdim, where)
        if isinstance(where, str):
            if where not in self.tag_names:
                raise MissingBoundary(
                    f"boundary {where!r} is not a physical group of this mesh; "
                    f"known names: {sorted(self.tag_names) or 'none'}"
                )
            tag = self.tag_names[where]
        else:
            tag = int(where)
        if self.facet_tags is None:
            raise MissingBoundary(f"boundary tag {where!r} given but the problem has no facet_tags")
        present = self.domain.comm.allreduce(int(np.any(self.facet_tags.values == tag)), MPI.MAX)
        if not present:
            raise MissingBoundary(
                f"boundary {where!r} (tag {tag}) has no facets in the mesh's facet tags; "
                f"tags present: {sorted(set(self.domain.comm.allreduce(list(np.unique(self.facet_tags.values)), MPI.SUM)))}"
            )
        return self.facet_tags.find(tag)

    # ---- conditions -------------------------------------------------------------------
    def _constant(self, value, shape):
        if isinstance(value, fem.Constant) or isinstance(value, ufl.core.expr.Expr):
            return value
        arr = np.array(value, dtype=default_scalar_type)  # own, C-contiguous copy
        if arr.shape != shape:
            raise ValueError(f"value {value!r} has shape {arr.shape}, expected {shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"value {value!r} is not finite")
        return fem.Constant(self.domain, arr)

    def _shape(self, field: str):
        if field == "u":
            return (self.gdim,)
        return () if self.gdim == 2 else (3,)

    def fix(self, where: Where, component: str = "u", value=0.0):
        """Dirichlet condition on a component (``u``, ``u_x``, ``phi``, ``phi_z``, ...).

        ``value`` is a number (or a vector for ``u``/``phi`` in 3D), a ``fem.Constant``
        (update ``.value`` for load stepping), or a callable ``x -> values`` interpolated
        into the component's space. Returns the constant or function holding the value
        (a list of scalar constants for a constant vector on ``u`` or 3D ``phi``).
        """
        Vi = sub_space(self.V, component)
        fdim = self.domain.topology.dim - 1
        field, sub = COMPONENTS[self.gdim][component]
        shape = () if sub is not None else self._shape("u" if field == 0 else "phi")
        if shape and not callable(value):
            # dolfinx takes Constant values only per scalar component of a mixed space
            names = [n for n, (f, s) in COMPONENTS[self.gdim].items() if f == field and s is not None]
            values = np.broadcast_to(np.asarray(value, dtype=float), shape)
            return [self.fix(where, n, float(v)) for n, v in zip(names, values)]
        facets = self.facets(where)
        if callable(value) and not isinstance(value, fem.Constant):
            Vc, _ = Vi.collapse()
            g = fem.Function(Vc)
            g.interpolate(value)
            dofs = fem.locate_dofs_topological((Vi, Vc), fdim, facets)
            self.bcs.append(fem.dirichletbc(g, dofs, Vi))
            holder = g
        else:
            holder = self._constant(value, shape)
            dofs = fem.locate_dofs_topological(Vi, fdim, facets)
            self.bcs.append(fem.dirichletbc(holder, dofs, Vi))
        self._snes = None
        return holder

    def traction(self, where: Where, value):
        """Surface traction t [Pa] (vector, or a UFL expression) on a boundary."""
        holder = self._constant(value, (self.gdim,))
        self._surface.append((self.facets(where), "u", holder))
        self._snes = None
        return holder

    def surface_couple(self, where: Where, value):
        """Surface couple [N/m] (scalar phi_z-couple in 2D, vector in 3D) on a boundary."""
        holder = self._constant(value, self._shape("phi"))
        self._surface.append((self.facets(where), "phi", holder))
        self._snes = None
        return holder

    def body_force(self, value):
        """Body force per unit volume [N/m^3] (vector or UFL expression)."""
        holder = self._constant(value, (self.gdim,))
        self._volume.append(("u", holder))
        self._snes = None
        return holder

    def body_couple(self, value):
        """Body couple per unit volume [N/m^2]."""
        holder = self._constant(value, self._shape("phi"))
        self._volume.append(("phi", holder))
        self._snes = None
        return holder

    # ---- forms ------------------------------------------------------------------------
    def _ds(self):
        fdim = self.domain.topology.dim - 1
        pieces = [f for f, _, _ in self._surface]
        if not pieces:
            return ufl.Measure("ds", domain=self.domain)
        indices = np.concatenate(pieces).astype(np.int32)
        values = np.concatenate([np.full(len(f), i + 1, dtype=np.int32) for i, f in enumerate(pieces)])
        if len(np.unique(indices)) != len(indices):
            raise ValueError("two surface loads act on the same facets; combine them into one")
        order = np.argsort(indices)
        tags = _mesh.meshtags(self.domain, fdim, indices[order], values[order])
        return ufl.Measure("ds", domain=self.domain, subdomain_data=tags)

    def external_work(self, du, dphi):
        """External virtual work of the surface and volume loads (UFL form or 0)."""
        ds = self._ds()
        L = 0
        for i, (_, field, value) in enumerate(self._surface):
            L += ufl.inner(value, du if field == "u" else dphi) * ds(i + 1)
        for field, value in self._volume:
            L += ufl.inner(value, du if field == "u" else dphi) * self.dx
        return L

    def residual(self, w: fem.Function | None = None):
        """Static residual form ``internal - external`` for test functions of V."""
        w = self.w if w is None else w
        u, phi = ufl.split(w)
        du, dphi = ufl.TestFunctions(self.V)
        F = internal_work(u, phi, du, dphi, self.constants) * self.dx
        L = self.external_work(du, dphi)
        return F - L if L != 0 else F

    def stress_expressions(self, w: fem.Function | None = None):
        """(sigma, m) of ``w`` as UFL expressions."""
        u, phi = ufl.split(self.w if w is None else w)
        return stresses(u, phi, self.constants)

    # ---- solve ------------------------------------------------------------------------
    def snes_problem(self, F, prefix: str):
        """A configured :class:`NonlinearProblem` for a residual F in ``self.w``."""
        nullspace = rigid_body_modes(self.V) if self.solver_kind == "iterative" else None
        return make_snes_problem(F, self.w, self.bcs, prefix, self.petsc_options,
                                 near_nullspace=nullspace)

    def solve(self) -> int:
        """Solve for ``self.w``; return SNES iterations; on failure restore the last good state."""
        if self._snes is None:
            self._snes = self.snes_problem(self.residual(), self.prefix)
        self._snes.solve()
        return self.checked(self._snes, "static micropolar solve")

    def checked(self, snes_problem, what: str) -> int:
        """SNES iterations of a converged solve of ``w`` (else raise, restoring the last
        converged state)."""
        return self._checked(lambda: check_converged(snes_problem, what), what)

    def checked_ksp(self, ksp, what: str) -> int:
        """1 for a converged linear solve of ``w`` (else raise as :meth:`checked`)."""
        return self._checked(lambda: check_ksp_converged(ksp, what), what)

    def _checked(self, check, what: str) -> int:
        try:
            its = check()
        except Exception as err:
            self.w.x.array[:] = self._last_good
            self.w.x.scatter_forward()
            where = self.write_checkpoint()
            if where is not None:
                err.args = (f"{err.args[0]}; last converged state written to {where}",)
            raise
        if not np.all(np.isfinite(self.w.x.array)):
            self.w.x.array[:] = self._last_good
            raise FloatingPointError(f"{what}: solution has NaN/Inf; last converged state restored")
        self._last_good[:] = self.w.x.array
        return its

    def write_checkpoint(self, directory: str | Path | None = None) -> Path | None:
        """Write the current state: owned dof values and their global indices, one file per rank."""
        directory = self.checkpoint_dir if directory is None else Path(directory)
        if directory is None:
            return None
        comm = self.domain.comm
        if comm.rank == 0:
            directory.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        imap = self.V.dofmap.index_map
        bs = self.V.dofmap.index_map_bs
        n = imap.size_local * bs
        np.savez(directory / f"continuum_rank{comm.rank}_of{comm.size}.npz",
                 values=self.w.x.array[:n],
                 global_dofs=imap.local_to_global(np.arange(imap.size_local, dtype=np.int32)))
        return directory

    def read_checkpoint(self, directory: str | Path) -> None:
        """Restore a state written by :meth:`write_checkpoint` on the same partition."""
        comm = self.domain.comm
        path = Path(directory) / f"continuum_rank{comm.rank}_of{comm.size}.npz"
        if not path.exists():
            raise FileNotFoundError(f"no checkpoint {path} (written with a different rank count?)")
        data = np.load(path)
        n = len(data["values"])
        self.w.x.array[:n] = data["values"]
        self.w.x.scatter_forward()
        self._last_good[:] = self.w.x.array
