"""Explicit dynamics of a continuum model: central differences on a lumped mass.

An implicit step of a plastic model solves a nonlinear system (the return mapping inside
every residual, a dozen quasi-Newton iterations in the 3D chamber, each a residual and a
pair of triangular solves: 26x the elastic step, whose one solve reuses one factorisation).
Explicit dynamics (Belytschko, Liu & Moran 2014, ch. 6; what LS-DYNA and Abaqus/Explicit
do for plasticity) replaces the solve by the lumped mass: a step is one residual and a
division, the return mapping runs once a step at each quadrature point and is committed
(no iterations, no tangent). The price is the stability limit ``dt <= 2 / omega_max``
(omega_max the highest frequency of the lumped-mass, elastic-stiffness pair): a step
longer than that is split into equal substeps, so a caller keeps its own step (the coupled
run's FE step of N DEM steps).

The scheme (velocity Verlet, second order, energy-conserving for a linear elastic body up
to a bounded O(h^2) oscillation; no numerical damping)::

    v_{n+1/2} = v_n + h/2 a_n,    w_{n+1} = w_n + h v_{n+1/2},
    a_{n+1} = M_L^-1 (f_ext - f_int(w_{n+1})),    v_{n+1} = v_{n+1/2} + h/2 a_{n+1},

with ``M_L`` the row sums of the model's consistent mass (positive for degree-1 fields;
higher degrees have negative row sums on tetrahedra and are refused). Within a step of
``k`` substeps the Dirichlet values move linearly from their last values to the ones set
for the step's end, the loads are held at the step's end values (:meth:`load_time`), and
a history model's state is committed after every substep (its return mapping from the
last substep's state). :meth:`solve` may be repeated (a staggered coupling's iterations):
it starts again from the step's start, whose fields and committed state :meth:`predict`
kept.

Optional mass-proportional damping ``C = alpha M_L`` (``damping`` alpha [1/s]): the force
``-alpha M_L v`` at the half-step velocity, so a mode of frequency omega decays at the
damping ratio ``xi = alpha / (2 omega)`` and its energy as ``exp(-alpha t)``: it damps the
low modes (a body's ringing), as a granular far field's material damping does, and leaves
the high ones; the stability limit becomes ``2 / omega_max (sqrt(1 + xi^2) - xi)``.

The stability limit is measured, not guessed: ``omega_max^2`` is the largest eigenvalue of
``M_L^-1 K`` (K the elastic stiffness, without Dirichlet conditions, which can only lower
it) by power iteration, its Rayleigh quotient a lower bound that the iteration closes to
within :data:`POWER_TOL`; the substeps take ``safety`` of the limit.
"""

from __future__ import annotations

import math

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem

from granfe.dynamics import EnergyForms
from granfe.problem import ContinuumProblem

__all__ = ["CentralDifference", "POWER_TOL"]

#: relative change of the power iteration's eigenvalue estimate at which it stops
POWER_TOL = 1e-4


class CentralDifference:
    """Explicit time stepper over a :class:`ContinuumProblem` (its BCs, loads, weight).

    The interface of :class:`granfe.dynamics.GeneralizedAlpha`: set the loads for
    :meth:`load_time` and the Dirichlet values for the step's end, then :meth:`step` (or
    :meth:`predict`, :meth:`solve` as often as needed, :meth:`finish`).

    Args:
        problem: the continuum (degree-1 fields).
        dt: the step [s]; split into substeps of at most ``safety`` times the stability
            limit.
        safety: fraction of the stability limit a substep may take, in (0, 1].
        max_substeps: refuse a step that needs more (a mistaken dt or modulus).
        damping: mass-proportional damping alpha [1/s] (>= 0; the module docstring).
    """

    def __init__(self, problem: ContinuumProblem, dt: float, safety: float = 0.9,
                 max_substeps: int = 1000, damping: float = 0.0):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
        if not (np.isfinite(damping) and damping >= 0):
            raise ValueError(f"damping (mass-proportional, 1/s) must be >= 0, got {damping!r}")
        self.damping = float(damping)
        if not (0 < safety <= 1):
            raise ValueError(f"safety (fraction of the stability limit) must lie in (0, 1], got {safety!r}")
        if any(d != 1 for d in problem.degree):
            raise ValueError(f"CentralDifference needs degree-1 fields (a lumped mass by row sums), "
                             f"got degrees {problem.degree}")
        self.problem, self.safety, self.max_substeps = problem, float(safety), int(max_substeps)
        self.t = 0.0
        self.dt = fem.Constant(problem.domain, float(dt))
        V, model, jit = problem.V, problem.model, problem.jit_options
        self.w_old = fem.Function(V, name="w_old")
        self.v = fem.Function(V, name="velocity")
        self.a = fem.Function(V, name="acceleration")
        self._v0, self._a0 = fem.Function(V), fem.Function(V)
        dw = ufl.TestFunctions(V)
        self._forces = _forces(problem)
        ones = fem.Function(V)
        ones.x.array[:] = 1.0
        mass = fem.form(problem.weighted(model.inertia_work(problem.split(ones), dw)) * problem.dx,
                        jit_options=jit)
        lumped = fem.Function(V)
        _assemble_into(lumped.x.petsc_vec, mass)
        self.mass = lumped.x.array.copy()
        if self.mass.min() <= 0:
            raise ValueError("CentralDifference: a lumped mass is not positive (zero density or "
                             "partition weight somewhere?)")
        self._b = fem.Function(V)
        self._snapshot: dict[str, np.ndarray] | None = None
        self.fallbacks = 0                       # GeneralizedAlpha's counter, never used here
        self.substeps = 0
        self._omega_max: float | None = None
        self._energies = EnergyForms(problem, self.v)

    # ---- the stability limit --------------------------------------------------------
    @property
    def omega_max(self) -> float:
        """The highest circular frequency [rad/s] of the lumped-mass, elastic-stiffness pair."""
        if self._omega_max is None:
            self._omega_max = self._power_iteration()
        return self._omega_max

    @property
    def critical_time_step(self) -> float:
        """``2 / omega_max (sqrt(1 + xi^2) - xi)`` [s], ``xi = damping / (2 omega_max)``: the
        longest stable substep."""
        xi = self.damping / (2.0 * self.omega_max)
        return 2.0 / self.omega_max * (math.sqrt(1.0 + xi * xi) - xi)

    def substeps_for(self, dt: float) -> int:
        """Substeps of a step ``dt`` (each at most ``safety`` of the stability limit)."""
        k = max(1, math.ceil(dt / (self.safety * self.critical_time_step) - 1e-12))
        if k > self.max_substeps:
            raise ValueError(f"CentralDifference: a step of {dt:.4g} s needs {k} substeps of the "
                             f"stability limit {self.critical_time_step:.4g} s (max_substeps "
                             f"{self.max_substeps}): a shorter dt or a softer material")
        return k

    def _power_iteration(self, max_it: int = 500) -> float:
        from dolfinx.fem.petsc import assemble_matrix

        problem, model = self.problem, self.problem.model
        V = problem.V
        dw = ufl.TestFunctions(V)
        w = problem.split(problem.w)
        if hasattr(model, "elastic_work"):
            work = model.elastic_work(w, dw)
        else:
            work = model.internal_work(w, dw, problem.state.committed)
        F = problem.weighted(work) * problem.dx
        K = assemble_matrix(fem.form(ufl.derivative(F, problem.w, ufl.TrialFunction(V)),
                                     jit_options=problem.jit_options))
        K.assemble()
        n = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        inv_sqrt_m = 1.0 / np.sqrt(self.mass[:n])
        # symmetric form: M^-1/2 K M^-1/2 (K of an elastic model is symmetric)
        x, y = K.createVecRight(), K.createVecLeft()
        # a start of every mode, the same on any rank count (a function of the global index)
        first = V.dofmap.index_map.local_range[0] * V.dofmap.index_map_bs
        x.array[:] = 0.5 + np.modf((first + np.arange(n)) * 0.6180339887498949)[0]
        x.normalize()
        lam = 0.0
        for _ in range(max_it):
            x.array[:] *= inv_sqrt_m
            K.mult(x, y)
            y.array[:] *= inv_sqrt_m
            x.array[:] /= inv_sqrt_m
            new = y.dot(x)                          # Rayleigh quotient of a unit x
            y.copy(x)
            x.normalize()
            if lam > 0 and abs(new - lam) <= POWER_TOL * new:
                lam = new
                break
            lam = new
        for v in (K, x, y):
            v.destroy()
        if not (np.isfinite(lam) and lam > 0):
            raise RuntimeError(f"CentralDifference: the stiffness's largest eigenvalue came out {lam!r}")
        # the Rayleigh quotient approaches omega_max^2 from below: cover the rest of the
        # iteration's last change
        return math.sqrt(lam * (1 + 10 * POWER_TOL))

    # ---- stepping -------------------------------------------------------------------
    def initialize_acceleration(self) -> None:
        """``a_0 = M_L^-1 (f_ext - f_int(w_0))`` (zero on Dirichlet dofs; the state stays)."""
        self._forces.start()
        self._accelerate(self.a.x.array, commit=False)

    def load_time(self) -> float:
        """The time of the step's end, at which the loads are held through its substeps."""
        return self.t + float(self.dt.value)

    def predict(self) -> None:
        """Start a step: keep its starting fields and committed state (for :meth:`solve`)."""
        self.w_old.x.array[:] = self.problem.w.x.array
        self._v0.x.array[:] = self.v.x.array
        self._a0.x.array[:] = self.a.x.array
        self._snapshot = self.problem.state.state_dict()

    def solve(self) -> int:
        """Advance from the step's start to its end; returns the substeps taken."""
        if self._snapshot is None:
            raise RuntimeError("CentralDifference.solve before predict")
        problem = self.problem
        w, v, a = problem.w.x.array, self.v.x.array, self.a.x.array
        w0 = self.w_old.x.array
        end = w0.copy()
        for bc in problem.bcs:                # the Dirichlet values set for the step's end
            bc.set(end)
        fixed = self._fixed_dofs()
        dt = float(self.dt.value)
        k = self.substeps_for(dt)
        h = dt / k
        w[:] = w0
        v[:] = self._v0.x.array
        a[:] = self._a0.x.array
        problem.state.load_state(self._snapshot)
        self._forces.start()
        rate = (end[fixed] - w0[fixed]) / dt
        try:
            for j in range(1, k + 1):
                v += 0.5 * h * a
                w += h * v
                w[fixed] = w0[fixed] + (j / k) * (end[fixed] - w0[fixed])
                v[fixed] = rate
                self._accelerate(a, fixed)     # the return of this substep's fields, committed
                if self.damping:                # the damping force at the half-step velocity
                    a -= self.damping * v
                    a[fixed] = 0.0
                v += 0.5 * h * a
                if not np.isfinite(a).all():
                    raise FloatingPointError(f"CentralDifference: non-finite acceleration at "
                                             f"t = {self.t + j * h:.6g} s (substep {j} of {k})")
        except Exception:
            w[:] = w0
            problem.w.x.scatter_forward()
            problem.state.load_state(self._snapshot)
            raise
        self._forces.finish()
        self.substeps = k
        return k

    def finish(self) -> None:
        """Accept the step (its state is committed already)."""
        self.t += float(self.dt.value)
        self._snapshot = None

    def step(self) -> int:
        """Advance one step; return the substeps taken."""
        self.predict()
        k = self.solve()
        self.finish()
        return k

    def energies(self, weight=None) -> tuple[float, float]:
        """(kinetic, elastic) energy [J] (per unit thickness in 2D); the kinetic energy of the
        lumped mass, the one the scheme moves (``v . M_L v / 2``). With ``weight`` (a UFL
        expression, e.g. a region's indicator) both are the weighted integrals, the kinetic
        one of the consistent mass."""
        if weight is not None:
            return self._energies(weight)
        p = self.problem
        n = p.V.dofmap.index_map.size_local * p.V.dofmap.index_map_bs
        v = self.v.x.array[:n]
        stored = fem.assemble_scalar(self._energies.forms()[1])
        comm = p.domain.comm
        return (comm.allreduce(0.5 * float(np.dot(self.mass[:n] * v, v)), MPI.SUM), comm.allreduce(stored, MPI.SUM))

    # ---- internals ------------------------------------------------------------------
    def _fixed_dofs(self) -> np.ndarray:
        dofs = [bc.dof_indices()[0] for bc in self.problem.bcs]     # owned and ghost entries
        return np.unique(np.concatenate(dofs + [np.zeros(0, np.int32)]))

    def _accelerate(self, a: np.ndarray, fixed: np.ndarray | None = None, commit: bool = True) -> None:
        """``a = -M_L^-1 r(w)`` with r the residual (internal minus external forces), zero on
        the Dirichlet dofs; owned and ghost entries. With ``commit`` the state the return
        reached is committed."""
        self.problem.w.x.scatter_forward()
        self._forces.residual(self._b.x.petsc_vec, commit)
        a[:] = -self._b.x.array / self.mass
        a[self._fixed_dofs() if fixed is None else fixed] = 0.0


def _forces(problem: ContinuumProblem):
    """The cheapest residual the model allows: a matrix product for an affine model, the
    fused simplex kernel (degree-1 simplices, a model with ``simplex_forces``), else the
    model's UFL residual with the state's commit."""
    if _LinearForces.fits(problem):
        return _LinearForces(problem)
    if problem.state and hasattr(problem.model, "simplex_forces") and SimplexCells.fits(problem):
        return _SimplexForces(problem)
    return _FormForces(problem)


def _assemble_into(b: PETSc.Vec, form) -> None:
    from dolfinx.fem.petsc import assemble_vector

    with b.localForm() as loc:
        loc.set(0.0)
    assemble_vector(b, form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)


class _FormForces:
    """The model's residual form (its UFL return, if any, from the committed state), the
    state committed before it is assembled."""

    def __init__(self, problem: ContinuumProblem):
        self.problem = problem
        self.form = fem.form(problem.residual(), jit_options=problem.jit_options)

    def start(self) -> None:
        pass

    def finish(self) -> None:
        pass

    def residual(self, b: PETSc.Vec, commit: bool) -> None:
        if hasattr(self.problem.model, "evaluate_points"):
            self.problem.model.evaluate_points(self.problem)    # its return, at these fields
        if commit and self.problem.state:
            self.problem.state.commit()
        _assemble_into(b, self.form)


class _LinearForces:
    """The residual ``K w - L`` of an affine model without history: the stiffness K (weighted,
    no Dirichlet conditions, stored zeros dropped) assembled once and again only when one of
    its constants changes, one matrix product a substep; the loads L assembled once a step
    (they are held through its substeps). The UFL residual costs an assembly a substep (in
    the 3D chamber, 10.6k dofs: 5.5 ms against 0.35 ms for the product), and the product is
    as parallel as the mesh, in a fixed order: the same bits run to run on a rank count."""

    @staticmethod
    def fits(problem: ContinuumProblem) -> bool:
        from ufl.algorithms import expand_derivatives, extract_coefficients
        from ufl.algorithms.formtransformations import compute_form_arities

        model = problem.model
        if not model.linear or problem.state or model.fixed_fields():
            return False
        w = problem.w
        J = expand_derivatives(ufl.derivative(problem.residual(), w, ufl.TrialFunction(problem.V)))
        # the partition weight is fixed once set (ContinuumProblem.set_weight)
        fixed = set() if problem.weight is None else set(extract_coefficients(ufl.as_ufl(problem.weight)))
        L = problem.external_work(ufl.TestFunctions(problem.V))
        if set(J.coefficients()) - fixed or (L != 0 and w in L.coefficients()):
            return False
        # the internal work bilinear (a term without w, e.g. a prestress, would be lost)
        try:
            return compute_form_arities(expand_derivatives(_LinearForces._stiffness(problem))) == {2}
        except ValueError:
            return False

    @staticmethod
    def _stiffness(problem: ContinuumProblem):
        V = problem.V
        return problem.weighted(problem.model.internal_work(ufl.TrialFunctions(V), ufl.TestFunctions(V),
                                                            problem.state.committed)) * problem.dx

    def __init__(self, problem: ContinuumProblem):
        self.problem = problem
        V, jit = problem.V, problem.jit_options
        dw = ufl.TestFunctions(V)
        k_ufl = self._stiffness(problem)
        self._k = fem.form(k_ufl, jit_options=jit)
        self._constants = list(k_ufl.constants())
        L = problem.external_work(dw)
        self._l = None if L == 0 else fem.form(L, jit_options=jit)
        self.load = fem.Function(V)
        self.K, self._key = None, None

    def start(self) -> None:
        from dolfinx.fem.petsc import assemble_matrix

        from granfe.dynamics import _without_zeros

        key = tuple(np.asarray(c.value).tobytes() for c in self._constants)
        if key != self._key:
            A = assemble_matrix(self._k)
            A.assemble()
            if self.K is not None:
                self.K.destroy()
            self.K, self._key = _without_zeros(A), key
            A.destroy()
        if self._l is not None:
            _assemble_into(self.load.x.petsc_vec, self._l)

    def finish(self) -> None:
        pass

    def residual(self, b: PETSc.Vec, commit: bool) -> None:
        self.K.mult(self.problem.w.x.petsc_vec, b)
        if self._l is not None:
            b.axpy(-1.0, self.load.x.petsc_vec)
        b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)


class SimplexCells:
    """The geometry a fused force kernel needs on degree-1 simplices (affine cells), owned
    cells only: per cell the basis gradients (vertices x gdim, constant on a simplex), the
    quadrature weights times |det J| times the partition weight at the points, the basis at
    the points (the problem's quadrature), and per field the local dofs (vertices x
    components)."""

    @staticmethod
    def fits(problem: ContinuumProblem) -> bool:
        domain = problem.domain
        return (domain.topology.cell_type.name in ("triangle", "tetrahedron")
                and domain.geometry.cmaps[0].degree == 1 and all(d == 1 for d in problem.degree))

    def __init__(self, problem: ContinuumProblem):
        import basix

        domain, V = problem.domain, problem.V
        self.gdim, tdim = problem.gdim, domain.topology.dim
        nc = domain.topology.index_map(tdim).size_local
        X = domain.geometry.x[domain.geometry.dofmaps[0][:nc]][:, :, :self.gdim]
        J = np.swapaxes(X[:, 1:, :] - X[:, :1, :], 1, 2)          # dx_i / dxi_j
        reference = np.vstack([-np.ones((1, tdim)), np.eye(tdim)])  # dN_a / dxi_j
        self.grads = np.ascontiguousarray(reference @ np.linalg.inv(J))   # (cells, vertices, gdim)
        points, weights = basix.make_quadrature(domain.basix_cell(), problem.state.degree)
        state_points = next(iter(problem.state.committed.values())).function_space.element.interpolation_points
        if not np.allclose(points, state_points, rtol=0, atol=1e-14):
            raise RuntimeError("SimplexCells: basix's quadrature is not the state's")
        self.N = np.hstack([1 - points.sum(axis=1, keepdims=True), points])
        wdet = weights[None, :] * np.abs(np.linalg.det(J))[:, None]
        if problem.weight is not None:         # fixed once set (ContinuumProblem.set_weight)
            cells = np.arange(nc, dtype=np.int32)
            wdet = wdet * fem.Expression(problem.weight, points).eval(domain, cells).reshape(nc, -1)
        self.wdet = np.ascontiguousarray(wdet)
        self.dofs = {}
        for i, field in enumerate(problem.fields):
            sub = V.sub(i)
            lists = ([sub.sub(k).dofmap.list[:nc] for k in range(len(field.components))]
                     if field.shape else [sub.dofmap.list[:nc]])
            self.dofs[field.name] = np.ascontiguousarray(np.stack(lists, axis=2)).astype(np.int64)


class _SimplexForces:
    """The model's fused simplex kernel (``simplex_forces``): kinematics, the return and the
    element forces in one pass over the owned cells, the state updated in place; the loads
    assembled once a step (they are held through its substeps)."""

    def __init__(self, problem: ContinuumProblem):
        self.problem = problem
        self.cells = SimplexCells(problem)
        dw = ufl.TestFunctions(problem.V)
        L = problem.external_work(dw)
        self.load_form = None if L == 0 else fem.form(L, jit_options=problem.jit_options)
        self.load = None
        state = problem.state
        npts = self.cells.wdet.size
        self.views = {}
        for name, f in state.committed.items():
            bs = f.function_space.dofmap.index_map_bs
            rows = f.function_space.dofmap.list[:self.cells.wdet.shape[0]].ravel()
            if not np.array_equal(rows, np.arange(npts)):
                raise RuntimeError(f"_SimplexForces: the quadrature dofs of {name!r} are not in cell order")
            self.views[name] = f.x.array[:npts * bs].reshape(npts, bs)
        self.scratch = {name: np.empty_like(v) for name, v in self.views.items()}
        self.local = None

    def start(self) -> None:
        if self.load_form is not None:
            if self.load is None:
                self.load = fem.Function(self.problem.V)
            _assemble_into(self.load.x.petsc_vec, self.load_form)

    def finish(self) -> None:
        for f in self.problem.state.committed.values():     # the ghost cells' from their owners
            f.x.scatter_forward()

    def residual(self, b: PETSc.Vec, commit: bool) -> None:
        with b.localForm() as loc:
            f = loc.array_w
            f[:] = 0.0
            new = self.views if commit else self.scratch
            self.problem.model.simplex_forces(self.cells, self.problem.w.x.array, self.views, new, f)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        if self.load is not None:
            n = len(b.array)
            b.array_w[:] -= self.load.x.array[:n]
        b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
