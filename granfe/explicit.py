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
    """

    def __init__(self, problem: ContinuumProblem, dt: float, safety: float = 0.9,
                 max_substeps: int = 1000):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
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
        # a history model with a return at points (numba): the residual reads the stresses it
        # stored; else the model's residual with its UFL return, and the state's commit
        self._points = _PointStress(problem) if problem.state and hasattr(model, "point_return") else None
        self._residual = self._points.residual if self._points else fem.form(problem.residual(), jit_options=jit)
        ones = fem.Function(V)
        ones.x.array[:] = 1.0
        mass = fem.form(problem.weighted(model.inertia_work(problem.split(ones), dw)) * problem.dx,
                        jit_options=jit)
        self.mass = _assembled(mass)
        if self.mass.min() <= 0:
            raise ValueError("CentralDifference: a lumped mass is not positive (zero density or "
                             "partition weight somewhere?)")
        self._b = fem.Function(V)
        self._snapshot: dict[str, np.ndarray] | None = None
        self.fallbacks = 0                       # GeneralizedAlpha's counter, never used here
        self.substeps = 0
        self._omega_max: float | None = None
        self._elastic = fem.form(model.stored_energy(problem.split(problem.w), problem.state.committed)
                                 * problem.dx, jit_options=jit)

    # ---- the stability limit --------------------------------------------------------
    @property
    def omega_max(self) -> float:
        """The highest circular frequency [rad/s] of the lumped-mass, elastic-stiffness pair."""
        if self._omega_max is None:
            self._omega_max = self._power_iteration()
        return self._omega_max

    @property
    def critical_time_step(self) -> float:
        """``2 / omega_max`` [s]: the longest stable substep."""
        return 2.0 / self.omega_max

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
        """``a_0 = M_L^-1 (f_ext - f_int(w_0))`` (zero on Dirichlet dofs)."""
        if self._points is not None:
            self._points.update(commit=False)
        self._accelerate(self.a.x.array)

    def load_time(self) -> float:
        """The time of the step's end, at which the loads are held through its substeps."""
        return self.t + float(self.dt.value)

    def predict(self) -> None:
        """Start a step: keep its starting fields and committed state (for :meth:`solve`)."""
        self.w_old.x.array[:] = self.problem.w.x.array
        self._v0.x.array[:] = self.v.x.array
        self._a0.x.array[:] = self.a.x.array
        state = self.problem.state
        self._snapshot = {k: f.x.array.copy() for k, f in state.committed.items()} if state else {}

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
        self._restore_state()
        rate = (end[fixed] - w0[fixed]) / dt
        try:
            for j in range(1, k + 1):
                v += 0.5 * h * a
                w += h * v
                w[fixed] = w0[fixed] + (j / k) * (end[fixed] - w0[fixed])
                v[fixed] = rate
                if self._points is not None:
                    self._points.update()      # the return mapping of this substep's fields
                elif problem.state:
                    problem.state.commit()
                self._accelerate(a, fixed)
                v += 0.5 * h * a
                if not np.isfinite(a).all():
                    raise FloatingPointError(f"CentralDifference: non-finite acceleration at "
                                             f"t = {self.t + j * h:.6g} s (substep {j} of {k})")
        except Exception:
            w[:] = w0
            problem.w.x.scatter_forward()
            self._restore_state()
            raise
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
        lumped mass, the one the scheme moves (``v . M_L v / 2``)."""
        if weight is not None:
            raise NotImplementedError("CentralDifference.energies: a weighted energy is not "
                                      "implemented (GeneralizedAlpha has it)")
        comm = self.problem.domain.comm
        n = self.problem.V.dofmap.index_map.size_local * self.problem.V.dofmap.index_map_bs
        v = self.v.x.array[:n]
        kinetic = 0.5 * float(np.dot(self.mass[:n] * v, v))
        return (comm.allreduce(kinetic, MPI.SUM), comm.allreduce(fem.assemble_scalar(self._elastic), MPI.SUM))

    # ---- internals ------------------------------------------------------------------
    def _fixed_dofs(self) -> np.ndarray:
        dofs = [bc.dof_indices()[0] for bc in self.problem.bcs]     # owned and ghost entries
        return np.unique(np.concatenate(dofs + [np.zeros(0, np.int32)]))

    def _restore_state(self) -> None:
        state = self.problem.state
        for name, values in (self._snapshot or {}).items():
            state.committed[name].x.array[:] = values
            state.trial[name].x.array[:] = values

    def _accelerate(self, a: np.ndarray, fixed: np.ndarray | None = None) -> None:
        """``a = -M_L^-1 r(w)`` with r the residual (internal minus external forces), zero on
        the Dirichlet dofs; owned and ghost entries."""
        from dolfinx.fem.petsc import assemble_vector

        self.problem.w.x.scatter_forward()
        b = self._b.x.petsc_vec
        with b.localForm() as loc:
            loc.set(0.0)
        assemble_vector(b, self._residual)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        a[:] = -self._b.x.array / self.mass
        a[self._fixed_dofs() if fixed is None else fixed] = 0.0


class _PointStress:
    """A history model's return mapping at the quadrature points (the model's
    ``point_kinematics``, ``point_return``, ``point_work``): the kinematics evaluated at the
    owned cells' points, the return, the new state written as committed (and trial), the
    stresses into quadrature functions that the residual integrates."""

    def __init__(self, problem: ContinuumProblem):
        import basix.ufl

        model, state, jit = problem.model, problem.state, problem.jit_options
        domain = problem.domain
        self.problem = problem
        Q = next(iter(state.committed.values())).function_space
        self.expression = fem.Expression(model.point_kinematics(problem.split(problem.w)),
                                         Q.element.interpolation_points, jit_options=jit)
        tdim = domain.topology.dim
        self.cells = np.arange(domain.topology.index_map(tdim).size_local, dtype=np.int32)
        self.stresses = {}
        for name, shape in model.point_stress_shapes(problem.gdim).items():
            S = fem.functionspace(domain, basix.ufl.quadrature_element(
                domain.basix_cell(), value_shape=shape, degree=state.degree))
            self.stresses[name] = fem.Function(S, name=f"point_{name}")
        dw = ufl.TestFunctions(problem.V)
        F = problem.weighted(model.point_work(self.stresses, dw)) * problem.dx
        L = problem.external_work(dw)
        self.residual = fem.form(F - L if L != 0 else F, jit_options=jit)
        self._rows = {}
        for f in (*state.committed.values(), *self.stresses.values()):
            rows = f.function_space.dofmap.list[:len(self.cells)].ravel()
            self._rows[id(f)] = (rows, f.function_space.dofmap.index_map_bs,
                                 bool(np.array_equal(rows, np.arange(len(rows)))))
        self._scratch = {name: np.empty_like(self._owned(f)) for name, f in state.committed.items()}

    def _owned(self, f: fem.Function) -> np.ndarray:
        """The owned cells' point values of a quadrature function, (points, bs): a view where
        the dofs of the owned cells run in order (dolfinx numbers a quadrature space so),
        else a copy (then :meth:`_put` writes back)."""
        rows, bs, in_order = self._rows[id(f)]
        if in_order:
            return f.x.array[:len(rows) * bs].reshape(len(rows), bs)
        return f.x.array.reshape(-1, bs)[rows]

    def _put(self, f: fem.Function, values: np.ndarray) -> None:
        rows, bs, in_order = self._rows[id(f)]
        if not in_order:
            f.x.array.reshape(-1, bs)[rows] = values
        f.x.scatter_forward()

    def update(self, commit: bool = True) -> None:
        """The stresses of the current fields from the committed state; with ``commit`` the
        returned state becomes the committed one (the trial state, which lives only between a
        state's evaluate and commit, is left alone). Collective."""
        kinematics = self.expression.eval(self.problem.domain, self.cells)
        kinematics = kinematics.reshape(-1, self.expression.value_size)
        state = self.problem.state
        old = {name: self._owned(f) for name, f in state.committed.items()}
        new = old if commit else self._scratch
        stresses = {name: self._owned(f) for name, f in self.stresses.items()}
        self.problem.model.point_return(kinematics, old, new, stresses)
        for name, f in self.stresses.items():
            self._put(f, stresses[name])
        if commit:
            for name, f in state.committed.items():
                self._put(f, new[name])


def _assembled(form) -> np.ndarray:
    """A vector form assembled, owned and ghost entries (the owners' sums)."""
    from dolfinx.fem.petsc import assemble_vector

    b = assemble_vector(form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    with b.localForm() as loc:
        out = loc.array.copy()
    b.destroy()
    return out
