"""Static boundary-value problem of any continuum model: conditions, loads, SNES solve.

Typical use (2D plane strain, mesh with named physical groups from gmsh)::

    problem = MicropolarProblem(mesh, material, facet_tags=ft, tag_names={"left": 1, ...})
    problem.fix("left", "u_x"); problem.fix("left", "phi")
    problem.traction("right", (1e6, 0.0))
    problem.solve()
    problem.reaction("left", "u_x")          # the support's reaction force

or, for any registered model, ``ContinuumProblem(mesh, StrainMemory(material), ...)``.
Boundaries are named physical groups, integer tags, or a locator ``x -> bool mask``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem
from dolfinx import mesh as _mesh

from granfe.materials import MicropolarMaterial
from granfe.models.base import ContinuumModel
from granfe.models.micropolar import Micropolar
from granfe.nodal import NodalLoad
from granfe.solvers import (
    ITERATIVE,
    REDUNDANT,
    check_converged,
    check_ksp_converged,
    make_snes_problem,
    rigid_modes_nullspace,
)
from granfe.spaces import components, model_space, split, sub_space
from granfe.state import QuadratureState

__all__ = ["ContinuumProblem", "MicropolarProblem", "MissingBoundary", "boundary_facets"]

Where = str | int | Callable[[np.ndarray], np.ndarray]


class MissingBoundary(ValueError):
    """A boundary named in a condition is not in the mesh's facet tags."""


def boundary_facets(domain, facet_tags, tag_names: dict, where: Where) -> np.ndarray:
    """Local boundary facet indices of ``where``: a named group of ``tag_names``, a tag value
    of ``facet_tags``, or a locator ``x -> bool``. Collective for tags (every rank checks the
    tag exists somewhere); :class:`MissingBoundary` names what is missing."""
    fdim = domain.topology.dim - 1
    if callable(where):
        return _mesh.locate_entities_boundary(domain, fdim, where)
    if isinstance(where, str):
        if where not in tag_names:
            raise MissingBoundary(
                f"boundary {where!r} is not a physical group of this mesh; "
                f"known names: {sorted(tag_names) or 'none'}"
            )
        tag = tag_names[where]
    else:
        tag = int(where)
    if facet_tags is None:
        raise MissingBoundary(f"boundary tag {where!r} given but there are no facet_tags")
    comm = domain.comm
    present = comm.allreduce(int(np.any(facet_tags.values == tag)), MPI.MAX)
    if not present:
        tags = sorted(set(comm.allreduce(list(np.unique(facet_tags.values)), MPI.SUM)))
        raise MissingBoundary(f"boundary {where!r} (tag {tag}) has no facets in the mesh's "
                              f"facet tags; tags present: {tags}")
    return facet_tags.find(tag)


class ContinuumProblem:
    """Quasi-static boundary-value problem of a continuum model on a 2D or 3D mesh.

    Args:
        domain: the mesh (2D in the plane or 3D).
        model: a :class:`~granfe.models.base.ContinuumModel` holding its material.
        facet_tags: boundary tags (e.g. from ``dolfinx.io.gmsh.model_to_mesh``).
        tag_names: physical-group names -> facet tag values.
        degree: Lagrange degree of each field (default: the model's).
        solver: ``"direct"`` (parallel MUMPS), ``"redundant"`` (every rank factorises the whole
            system with sequential MUMPS, :data:`granfe.solvers.REDUNDANT`: bit-identical run
            to run on the same rank count, for systems small enough to hold on one rank) or
            ``"iterative"`` (:data:`granfe.solvers.ITERATIVE`, with the model's rigid modes as
            near-nullspace).
        petsc_options: overrides of the solver's PETSc options.
        prefix: unique PETSc options prefix.
        checkpoint_dir: where the last converged state is written if a solve fails.
        quadrature_degree: of the history variables (models with state only; default
            twice the highest field degree).
    """

    def __init__(self, domain: _mesh.Mesh, model: ContinuumModel, *,
                 facet_tags: _mesh.MeshTags | None = None, tag_names: dict[str, int] | None = None,
                 degree: tuple[int, ...] | None = None, solver: str = "direct",
                 petsc_options: dict | None = None, prefix: str = "granfe_",
                 checkpoint_dir: str | Path | None = None, quadrature_degree: int | None = None):
        if not isinstance(model, ContinuumModel):
            raise TypeError(f"model must be a ContinuumModel, got {type(model).__name__}")
        if solver not in ("direct", "redundant", "iterative"):
            raise ValueError(f"solver must be 'direct', 'redundant' or 'iterative', got {solver!r}")
        self.domain = domain
        self.gdim = domain.geometry.dim
        model.bind(domain)
        self.model = model
        self.fields = model.fields(self.gdim)
        self.components = components(self.fields)
        self.degree = tuple(f.degree for f in self.fields) if degree is None else tuple(degree)
        self.V = model_space(domain, self.fields, self.degree)
        self.w = fem.Function(self.V, name="w")
        qdeg = 2 * max(self.degree) if quadrature_degree is None else quadrature_degree
        self.state = QuadratureState(domain, model.state_variables(self.gdim), qdeg)
        if self.state:
            self.state.bind(model.state_update(split(self.w, self.fields), self.state.committed),
                            jit_options=self.jit_options)
            self.dx = self.state.dx
        else:
            self.dx = ufl.Measure("dx", domain=domain)
        self.facet_tags = facet_tags
        self.tag_names = dict(tag_names or {})
        self.solver_kind = solver
        self.petsc_options = dict({"iterative": ITERATIVE, "redundant": REDUNDANT}.get(solver, {}))
        self.petsc_options.update(model.solver_options)
        self.petsc_options.update(petsc_options or {})
        self.prefix = prefix
        self.checkpoint_dir = None if checkpoint_dir is None else Path(checkpoint_dir)
        self.bcs: list[fem.DirichletBC] = []
        self._surface: list[tuple[np.ndarray, str, object]] = []
        self._volume: list[tuple[str, object]] = []
        self._work: list = []
        self._nodal: list[NodalLoad] = []
        self.weight = None
        self._snes = None
        self.last_good = self.w.x.array.copy()

    @property
    def material(self):
        return self.model.material

    @property
    def constants(self):
        return self.model.constants

    @property
    def snes(self):
        """The PETSc SNES of the last static solve (None before the first), e.g. to read its
        iteration counts or KSP."""
        return None if self._snes is None else self._snes.solver

    def invalidate(self) -> None:
        """Forget the compiled solver (after loads or conditions changed)."""
        self._snes = None

    # ---- where ------------------------------------------------------------------------
    def facets(self, where: Where) -> np.ndarray:
        """Local boundary facet indices of a named group, a tag value, or a locator."""
        return boundary_facets(self.domain, self.facet_tags, self.tag_names, where)

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

    def _field(self, name: str) -> int:
        for i, f in enumerate(self.fields):
            if f.name == name:
                return i
        raise ValueError(f"the {self.model.name} model has no field {name!r}; "
                         f"its fields: {[f.name for f in self.fields]}")

    def _component(self, component: str) -> tuple[int, int | None]:
        if component not in self.components:
            raise ValueError(f"unknown component {component!r} for the {self.gdim}D "
                             f"{self.model.name} model; choose one of {sorted(self.components)}")
        return self.components[component]

    def fix(self, where: Where, component: str = "u", value=0.0):
        """Dirichlet condition on a component (``u``, ``u_x``, ``phi``, ``phi_z``, ...).

        ``value`` is a number (or a vector for a vector field), a ``fem.Constant``
        (update ``.value`` for load stepping), or a callable ``x -> values`` interpolated
        into the component's space. Returns the constant or function holding the value
        (a list of scalar constants for a constant value on a whole vector field).
        """
        field, sub = self._component(component)
        f = self.fields[field]
        shape = () if sub is not None else f.shape
        if shape and not callable(value):
            # dolfinx takes Constant values only per scalar component of a mixed space
            # (flattened: a tensor field's components are listed in storage order)
            values = np.broadcast_to(np.asarray(value, dtype=float), shape).reshape(-1)
            return [self.fix(where, n, float(v)) for n, v in zip(f.components, values, strict=True)]
        return self._dirichlet(component, value, self.facets(where), topological=True)

    def fix_point(self, point, component: str = "u", value=0.0, tol: float | None = None):
        """Dirichlet condition at the dofs located at ``point`` (e.g. to hold a body under
        pure traction against rigid motion). Raises if no rank has a dof within ``tol``
        (default 1e-8 of the mesh size) of the point."""
        x0 = np.zeros(3)
        x0[:len(point)] = point
        field, sub = self._component(component)
        f = self.fields[field]
        if f.shape and sub is None and not callable(value):
            values = np.broadcast_to(np.asarray(value, dtype=float), f.shape).reshape(-1)
            return [self.fix_point(point, n, float(v), tol)
                    for n, v in zip(f.components, values, strict=True)]
        if tol is None:
            x = self.domain.geometry.x
            size = self.domain.comm.allreduce(float(np.ptp(x, axis=0).max()) if len(x) else 0.0,
                                              MPI.MAX)
            tol = 1e-8 * size

        def at(x):
            return np.linalg.norm(x - x0[:, None], axis=0) <= tol

        return self._dirichlet(component, value, at, topological=False)

    def fix_everywhere(self, component: str, value=0.0):
        """Dirichlet condition at every dof of a component, interior ones too (to hold a field
        the material leaves undetermined, e.g. chi of a micromorphic solid with only lam and
        mu). Returns the function holding the value."""
        return self._dirichlet(component, value, lambda x: np.full(x.shape[1], True), topological=False)

    def _dirichlet(self, component, value, where, topological: bool):
        Vi = sub_space(self.V, component, self.fields)
        fdim = self.domain.topology.dim - 1
        field, sub = self._component(component)
        shape = () if sub is not None else self.fields[field].shape
        needs_collapse = callable(value) and not isinstance(value, fem.Constant)
        if needs_collapse or not topological:
            Vc, _ = Vi.collapse()
        if topological:
            dofs = fem.locate_dofs_topological((Vi, Vc) if needs_collapse else Vi, fdim, where)
        else:
            dofs = fem.locate_dofs_geometrical((Vi, Vc), where)
            found = self.domain.comm.allreduce(len(dofs[0]), MPI.SUM)
            if not found:
                raise ValueError(f"no {component} dof lies at the point given to fix_point")
        if needs_collapse:
            holder = fem.Function(Vc)
            holder.interpolate(value)
            self.bcs.append(fem.dirichletbc(holder, dofs, Vi))
        elif topological:
            holder = self._constant(value, shape)
            self.bcs.append(fem.dirichletbc(holder, dofs, Vi))
        else:
            holder = fem.Function(Vc)
            holder.x.array[:] = float(value) if not isinstance(value, fem.Constant) else value.value
            self.bcs.append(fem.dirichletbc(holder, dofs, Vi))
        self._snes = None
        return holder

    def surface_load(self, where: Where, field: str, value):
        """A load per unit area on a boundary, work-conjugate to ``field`` (a traction for
        ``u``, a surface couple for ``phi``). Loads on the same or overlapping facets add."""
        holder = self._constant(value, self.fields[self._field(field)].shape)
        self._surface.append((self.facets(where), field, holder))
        self._snes = None
        return holder

    def body_load(self, field: str, value):
        """A load per unit volume work-conjugate to ``field``."""
        holder = self._constant(value, self.fields[self._field(field)].shape)
        self._volume.append((field, holder))
        self._snes = None
        return holder

    def volume_work(self, work) -> None:
        """A load given by its virtual work per unit volume: ``work(dw)``, a UFL scalar for
        the test functions ``dw`` (a tuple, one per field), e.g. a pore pressure's
        ``p div(du)`` or a source in a pressure field's equation."""
        self._work.append(work)
        self._snes = None

    def traction(self, where: Where, value):
        """Surface traction t [Pa] (vector, or a UFL expression) on a boundary."""
        return self.surface_load(where, "u", value)

    def surface_couple(self, where: Where, value):
        """Surface couple [N/m] (scalar phi_z-couple in 2D, vector in 3D) on a boundary."""
        return self.surface_load(where, "phi", value)

    def nodal_load(self, field: str = "u") -> NodalLoad:
        """A load given node by node on a degree-1 field (:class:`granfe.nodal.NodalLoad`:
        its ``set(F)`` takes nodal forces in V's dof layout, e.g. ``N^T f`` of point forces)."""
        load = NodalLoad(self.V, self.fields, field, self.degree[self._field(field)])
        self._nodal.append(load)
        self._snes = None
        return load

    def set_weight(self, weight) -> None:
        """Scale the material's internal and inertial work by ``weight`` (a UFL scalar, e.g. a
        DG0 function): 1 where the continuum is the material, a small positive number where
        another model carries it (the grains of a coupled window; seed 001's energy partition).
        Set before the first solve: a linear dynamic step assembles its matrices once."""
        self.weight = weight
        self._snes = None

    def weighted(self, integrand):
        """``integrand`` times the partition weight (:meth:`set_weight`), if any."""
        return integrand if self.weight is None else self.weight * integrand

    def body_force(self, value):
        """Body force per unit volume [N/m^3] (vector or UFL expression)."""
        return self.body_load("u", value)

    def body_couple(self, value):
        """Body couple per unit volume [N/m^2]."""
        return self.body_load("phi", value)

    # ---- forms ------------------------------------------------------------------------
    def _surface_measure(self):
        """Ds over the loaded facets, and per load the tags it integrates over. A facet's
        tag numbers the set of loads acting on it, so loads on overlapping facets add."""
        fdim = self.domain.topology.dim - 1
        if not self._surface:
            return ufl.Measure("ds", domain=self.domain), []
        acting: dict[int, set] = {}
        for i, (facets, _, _) in enumerate(self._surface):
            for f in facets:
                acting.setdefault(int(f), set()).add(i)
        signatures = self.domain.comm.allgather(sorted({tuple(sorted(s)) for s in acting.values()}))
        tag_of = {sig: k + 1 for k, sig in enumerate(sorted({s for part in signatures for s in part}))}
        indices = np.array(sorted(acting), dtype=np.int32)
        values = np.array([tag_of[tuple(sorted(acting[f]))] for f in indices], dtype=np.int32)
        tags = _mesh.meshtags(self.domain, fdim, indices, values)
        ds = ufl.Measure("ds", domain=self.domain, subdomain_data=tags)
        per_load = [tuple(t for sig, t in tag_of.items() if i in sig) for i in range(len(self._surface))]
        return ds, per_load

    def external_work(self, *dw):
        """External virtual work of the surface and volume loads (UFL form or 0) for test
        functions ``dw``, one per field (as arguments, or one tuple)."""
        if len(dw) == 1 and isinstance(dw[0], tuple):
            dw = dw[0]
        ds, per_load = self._surface_measure()
        names = [f.name for f in self.fields]
        L = 0
        for (_, field, value), tags in zip(self._surface, per_load, strict=True):
            if tags:
                L += ufl.inner(value, dw[names.index(field)]) * ds(tags)
        for field, value in self._volume:
            L += ufl.inner(value, dw[names.index(field)]) * self.dx
        for work in self._work:
            L += work(tuple(dw)) * self.dx
        for load in self._nodal:
            L += load.work(dw)
        return L

    def split(self, expr) -> tuple:
        """One UFL expression per field (see :func:`granfe.spaces.split`)."""
        return split(expr, self.fields)

    def residual(self, w: fem.Function | None = None):
        """Static residual form ``internal - external`` for test functions of V."""
        w = self.w if w is None else w
        dw = ufl.TestFunctions(self.V)
        F = self.weighted(self.model.internal_work(self.split(w), dw, self.state.committed)) * self.dx
        L = self.external_work(dw)
        return F - L if L != 0 else F

    def stresses(self, w: fem.Function | None = None) -> dict:
        """The model's named stress measures of ``w`` (UFL)."""
        return self.model.stresses(self.split(self.w if w is None else w), self.state.committed)

    def stress_expressions(self, w: fem.Function | None = None) -> tuple:
        """The stress measures as a tuple (micropolar: ``(sigma, m)``; index convention in
        :mod:`granfe.models.micropolar`)."""
        return tuple(self.stresses(w).values())

    # ---- reactions --------------------------------------------------------------------
    def _boundary_weights(self, where: Where, modes) -> list[np.ndarray]:
        """Per mode: a vector of V equal to the mode at the dofs on the boundary, else 0."""
        fdim = self.domain.topology.dim - 1
        facets = self.facets(where)
        on = np.zeros(len(self.w.x.array), dtype=bool)
        for i in range(len(self.fields)):
            on[fem.locate_dofs_topological(self.V.sub(i), fdim, facets)] = True
        out = []
        for mode in modes:
            g = fem.Function(self.V)
            for i, fn in enumerate(mode):
                if fn is not None:
                    g.sub(i).interpolate(fn)
            out.append(np.where(on, g.x.array, 0.0))
        return out

    def _reaction_work(self, where: Where, modes) -> np.ndarray:
        """Per mode, the virtual work of the reactions on the boundary (the residual, assembled
        once, against the mode restricted to the boundary's dofs). Collective."""
        from dolfinx.fem.petsc import assemble_vector

        b = assemble_vector(fem.form(self.residual(), jit_options=self.jit_options))
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        n = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        r = b.array_r[:n].copy()
        b.destroy()
        comm = self.domain.comm
        return np.array([comm.allreduce(float(r @ g[:n]), MPI.SUM)
                         for g in self._boundary_weights(where, modes)])

    def reaction(self, where: Where, component: str = "u"):
        """The reaction on a boundary, the force its supports exert on the body.

        The internal force minus the applied loads at the boundary's dofs, conjugate to
        ``component``: ``"u"`` the force vector [N, or N/m in 2D], ``"u_x"`` one component,
        ``"phi"`` the reaction couple. Collective."""
        field, sub = self._component(component)
        f = self.fields[field]
        n = int(np.prod(f.shape)) if f.shape else 1
        picks = [sub] if sub is not None else list(range(n))
        modes = []
        for k in picks:
            mode = [None] * len(self.fields)
            if f.shape:
                mode[field] = (lambda x, k=k: np.vstack([np.full(x.shape[1], float(i == k))
                                                         for i in range(n)]))
            else:
                mode[field] = lambda x: np.ones(x.shape[1])
            modes.append(mode)
        values = self._reaction_work(where, modes)
        return float(values[0]) if (sub is not None or not f.shape) else values

    def reaction_moment(self, where: Where, about=(0.0, 0.0, 0.0)):
        """The moment of the reactions (forces and couples) on a boundary about a point:
        a scalar (z) in 2D, a 3-vector in 3D. Uses the model's rigid modes (translations
        first, then rotations about the origin)."""
        work = self._reaction_work(where, self.model.rigid_modes(self.gdim))
        m0 = work[self.gdim:]
        force = np.zeros(3)
        force[:self.gdim] = work[:self.gdim]
        x0 = np.zeros(3)
        x0[:len(about)] = about
        shift = np.cross(x0, force)
        return float(m0[0] - shift[2]) if self.gdim == 2 else m0 - shift

    # ---- solve ------------------------------------------------------------------------
    def snes_problem(self, F, prefix: str, points_at=None):
        """A configured :class:`NonlinearProblem` for a residual F in ``self.w``;
        ``points_at``: the fields (a UFL expression of ``w``) F's stress is taken at, where a
        model that returns at the points evaluates them (None: ``w``)."""
        nullspace = None
        if self.solver_kind == "iterative":
            nullspace = rigid_modes_nullspace(self.V, self.model.rigid_modes(self.gdim))
        nlp = make_snes_problem(F, self.w, self.bcs, prefix, self.petsc_options,
                                near_nullspace=nullspace, jit_options=self.jit_options)
        if hasattr(self.model, "evaluate_points"):
            # a model whose return runs at the points (not in UFL): evaluate them at the
            # fields of every residual, before it is assembled
            from dolfinx.fem.petsc import assemble_residual, assign

            ctx = {"u": self.w, "residual": nlp.F, "jacobian": nlp.J, "bcs": self.bcs}

            def residual(snes, x, b):
                x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
                assign(x, self.w)
                self.model.evaluate_points(self, points_at)
                assemble_residual(snes, x, b, **ctx)

            nlp.solver.setFunction(residual, nlp.b)
        return nlp

    @property
    def jit_options(self) -> dict | None:
        """The model's JIT options for forms and expressions of this problem (None: dolfinx's)."""
        return dict(self.model.jit_options) or None

    def solver(self):
        """The PETSc SNES of :meth:`solve`, built if needed (e.g. to change its tolerances)."""
        if self._snes is None:
            self._snes = self.snes_problem(self.residual(), self.prefix)
        return self._snes.solver

    def residual_norm(self) -> float:
        """Norm of the static residual at the current ``w`` with the current loads and
        Dirichlet values (one assembly; the committed quadrature-point state). Collective."""
        snes = self.solver()
        x = self.w.x.petsc_vec.copy()
        f = x.duplicate()
        snes.computeFunction(x, f)
        norm = f.norm()
        x.destroy()
        f.destroy()
        return float(norm)

    def solve(self, commit: bool = True) -> int:
        """Solve for ``self.w``; return SNES iterations; on failure restore the last good
        state. ``commit``: accept the quadrature-point state of the solution (one load step)."""
        self.solver()
        self._snes.solve()
        its = self.checked(self._snes, "static solve")
        if commit:
            self.state.commit()
        return its

    def checked(self, snes_problem, what: str) -> int:
        """SNES iterations of a converged solve of ``w`` (else raise, restoring the last
        converged state)."""
        return self._checked(lambda: check_converged(snes_problem, what), what)

    def checked_ksp(self, ksp, what: str) -> int:
        """1 for a converged linear solve of ``w`` (else raise as :meth:`checked`)."""
        return self._checked(lambda: check_ksp_converged(ksp, what), what)

    def _restore(self) -> None:
        self.w.x.array[:] = self.last_good
        self.w.x.scatter_forward()
        self.state.restore()

    def _checked(self, check, what: str) -> int:
        try:
            its = check()
        except Exception as err:
            self._restore()
            where = self.write_checkpoint()
            if where is not None:
                err.args = (f"{err.args[0]}; last converged state written to {where}",)
            raise
        if not np.all(np.isfinite(self.w.x.array)):
            self._restore()
            raise FloatingPointError(f"{what}: solution has NaN/Inf; last converged state restored")
        self.last_good[:] = self.w.x.array
        return its

    # ---- state ------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        """This rank's owned dof values (and their global indices) and the committed
        quadrature-point state (``state/<name>``)."""
        imap = self.V.dofmap.index_map
        n = imap.size_local * self.V.dofmap.index_map_bs
        out = {"values": self.w.x.array[:n].copy(),
               "global_dofs": imap.local_to_global(np.arange(imap.size_local, dtype=np.int32))}
        out.update({f"state/{k}": v for k, v in self.state.state_dict().items()})
        return out

    def load_state(self, data) -> None:
        """Restore :meth:`state_dict` output of the same partition."""
        n = len(data["values"])
        size = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        if n != size:
            raise ValueError(f"the saved continuum state holds {n} dofs on this rank, the "
                             f"problem {size} (another mesh, degree or rank count?)")
        self.w.x.array[:n] = data["values"]
        self.w.x.scatter_forward()
        self.last_good[:] = self.w.x.array
        if self.state:
            self.state.load_state({k[len("state/"):]: data[k] for k in data if k.startswith("state/")})

    def write_checkpoint(self, directory: str | Path | None = None) -> Path | None:
        """Write :meth:`state_dict`, one file per rank."""
        directory = self.checkpoint_dir if directory is None else Path(directory)
        if directory is None:
            return None
        comm = self.domain.comm
        if comm.rank == 0:
            directory.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        np.savez(directory / f"continuum_rank{comm.rank}_of{comm.size}.npz", **self.state_dict())
        return directory

    def read_checkpoint(self, directory: str | Path) -> None:
        """Restore a state written by :meth:`write_checkpoint` on the same partition."""
        comm = self.domain.comm
        path = Path(directory) / f"continuum_rank{comm.rank}_of{comm.size}.npz"
        if not path.exists():
            raise FileNotFoundError(f"no checkpoint {path} (written with a different rank count?)")
        with np.load(path) as data:
            self.load_state({k: data[k] for k in data.files})


class MicropolarProblem(ContinuumProblem):
    """Quasi-static linear micropolar elasticity: a :class:`ContinuumProblem` of the
    :class:`~granfe.models.micropolar.Micropolar` model built from its material.

    ``degree`` is the pair of Lagrange degrees of (u, phi), default (2, 1).
    """

    def __init__(self, domain: _mesh.Mesh, material: MicropolarMaterial, *,
                 degree: tuple[int, int] = (2, 1), **kwargs):
        if not isinstance(material, MicropolarMaterial):
            raise TypeError(f"material must be a MicropolarMaterial, got {type(material).__name__}")
        super().__init__(domain, Micropolar(material), degree=degree, **kwargs)
