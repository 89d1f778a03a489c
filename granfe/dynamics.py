"""Implicit dynamics of a continuum model: generalized-alpha (Chung & Hulbert 1993).

The inertia is the model's (micropolar: mass ``rho`` on u, rotary inertia ``rho j`` on
phi). The spectral radius at infinite frequency ``rho_inf`` in [0, 1] is the one damping
parameter: ``rho_inf = 1`` gives alpha_m = alpha_f = 1/2, beta = 1/4, gamma = 1/2, the trapezoidal (Newmark
average acceleration) family, which conserves the energy of a linear elastic body
exactly; smaller values damp high frequencies with second-order accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem

from granfe.problem import ContinuumProblem
from granfe.solvers import ELASTIC_QUASI_NEWTON, REDUNDANT, fixed_jacobian, make_snes_problem

__all__ = ["AlphaParameters", "EnergyForms", "GeneralizedAlpha"]


@dataclass(frozen=True)
class AlphaParameters:
    """Generalized-alpha parameters from the high-frequency spectral radius ``rho_inf``."""

    rho_inf: float = 1.0

    def __post_init__(self):
        if not (0.0 <= self.rho_inf <= 1.0):
            raise ValueError(f"rho_inf (spectral radius at infinite frequency) must lie in [0, 1], "
                             f"got {self.rho_inf!r}")

    @property
    def alpha_m(self) -> float:
        return (2 * self.rho_inf - 1) / (self.rho_inf + 1)

    @property
    def alpha_f(self) -> float:
        return self.rho_inf / (self.rho_inf + 1)

    @property
    def gamma(self) -> float:
        return 0.5 + self.alpha_f - self.alpha_m

    @property
    def beta(self) -> float:
        return 0.25 * (1 + self.alpha_f - self.alpha_m) ** 2


class GeneralizedAlpha:
    """Time stepper over a :class:`ContinuumProblem` (its BCs, loads and solver options).

    Loads given to the problem as ``fem.Constant`` are evaluated at ``t_{n+1-alpha_f}``:
    update them (``.value``) before each :meth:`step` with :meth:`load_time`. A model's
    quadrature-point state is committed when a step is accepted (:meth:`finish`) and
    restored when its solve fails.

    ``tangent``: how a model with state and an elastic tangent (Drucker-Prager) solves a
    step with a direct solver: ``"elastic"``, quasi-Newton on the elastic Jacobian factorised
    once for the run (:class:`_ElasticQuasiNewton`; Newton if it fails, counted in
    :attr:`fallbacks`), or ``"consistent"``, Newton on the consistent tangent, assembled and
    factorised at every iteration. Both stop at the problem's SNES tolerances.
    """

    def __init__(self, problem: ContinuumProblem, dt: float, rho_inf: float = 1.0,
                 prefix: str | None = None, tangent: str = "elastic"):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be a positive number in s, got {dt!r}")
        if tangent not in ("elastic", "consistent"):
            raise ValueError(f"tangent must be 'elastic' or 'consistent', got {tangent!r}")
        self.problem = problem
        self.params = p = AlphaParameters(rho_inf)
        self.t = 0.0
        self.dt = fem.Constant(problem.domain, float(dt))
        V = problem.V
        self.w_old = fem.Function(V, name="w_old")
        self.v = fem.Function(V, name="velocity")
        self.a = fem.Function(V, name="acceleration")
        w, model, state = problem.w, problem.model, problem.state.committed
        dt_, b = self.dt, p.beta
        a_new = (w - self.w_old - dt_ * self.v) / (b * dt_**2) - (1 - 2 * b) / (2 * b) * self.a
        w_mid = (1 - p.alpha_f) * w + p.alpha_f * self.w_old
        a_mid = (1 - p.alpha_m) * a_new + p.alpha_m * self.a
        # a model returning at the quadrature points (not in UFL) evaluates them at the
        # residual's mid-point fields
        self._points_at = w_mid if hasattr(model, "evaluate_points") else None
        dw = ufl.TestFunctions(V)
        L = problem.external_work(dw)

        def residual(internal_work):
            F = problem.weighted(model.inertia_work(problem.split(a_mid), dw)
                                 + internal_work(problem.split(w_mid), dw, state)) * problem.dx
            return F - L if L != 0 else F

        F = residual(model.internal_work)
        # a linear model's Jacobian is the same at every step: factorise it once; a plastic
        # one's changes with the state (lagged, Newton degrades to a linear rate of ~0.8)
        options = ({"snes_lag_jacobian": -2, "snes_lag_jacobian_persists": True}
                   if model.linear and not problem.state else {})
        self._F, self._prefix = F, prefix or problem.prefix + "dyn_"
        self._newton = None
        # a pointwise model's quasi-Newton residual: the stress of its last evaluation, without
        # the tangent its Newton residual expands about (the same residual to round-off)
        F_quasi = residual(model.point_work) if hasattr(model, "point_work") else None
        self._quasi = (_ElasticQuasiNewton.build(self, F if F_quasi is None else F_quasi, w_mid, a_mid,
                                                 tangent=F_quasi is None)
                       if tangent == "elastic" else None)
        self._snes = self._newton_problem(options) if self._quasi is None else self._quasi.nlp
        self._affine = _AffineStep.build(self, F, L)
        self.fallbacks = 0
        #: the last solve: its SNES iterations, and with the quasi-Newton step whether it fell
        #: back to Newton (then also the quasi-Newton's iterations and PETSc reason)
        self.last_solve: dict = {}
        self._energies = EnergyForms(problem, self.v)

    def _newton_problem(self, options: dict | None = None, prefix: str | None = None):
        """Newton on the consistent tangent (the problem's solver options over ``options``)."""
        problem = self.problem
        saved, problem.petsc_options = problem.petsc_options, {**(options or {}), **problem.petsc_options}
        try:
            return problem.snes_problem(self._F, prefix or self._prefix, points_at=self._points_at)
        finally:
            problem.petsc_options = saved

    def initialize_acceleration(self) -> None:
        """Consistent initial acceleration ``M a_0 = f_ext - f_int(w_0)`` (zero on Dirichlet
        dofs, i.e. boundary values constant at the start)."""
        from dolfinx.fem.petsc import LinearProblem

        problem, model = self.problem, self.problem.model
        self._evaluate_points()
        V = problem.V
        dw = ufl.TestFunctions(V)
        lhs = problem.weighted(model.inertia_work(ufl.TrialFunctions(V), dw)) * problem.dx
        rhs = -problem.weighted(model.internal_work(problem.split(problem.w), dw,
                                                    problem.state.committed)) * problem.dx
        ext = problem.external_work(dw)
        if ext != 0:
            rhs = rhs + ext
        zero = fem.Function(V)
        bcs = [fem.dirichletbc(zero, bc.dof_indices()[0]) for bc in problem.bcs]
        lu = REDUNDANT if problem.solver_kind == "redundant" else {"pc_type": "lu",
                                                                   "pc_factor_mat_solver_type": "mumps"}
        solver = LinearProblem(lhs, rhs, bcs=bcs, u=self.a, petsc_options_prefix=f"granfe_a0_{id(self)}_",
                               petsc_options={"ksp_type": "preonly", **lu})
        solver.solve()

    def load_time(self) -> float:
        """The time at which loads of the next step are evaluated, ``t_{n+1-alpha_f}``."""
        return self.t + (1 - self.params.alpha_f) * self.dt.value

    def predict(self) -> None:
        """Start a step: keep the old state, put a constant-acceleration predictor in ``w``."""
        dt = float(self.dt.value)
        w = self.problem.w
        self.w_old.x.array[:] = w.x.array
        w.x.array[:] += dt * self.v.x.array + 0.5 * dt**2 * self.a.x.array

    def solve(self) -> int:
        """Solve the current step for ``w`` (may be repeated, e.g. by a staggered coupling).

        The step's equation is linear (linear material, loads independent of ``w``): with a
        direct solver it is one solve with the Jacobian factorised once (:class:`_AffineStep`).
        A plastic model with an elastic tangent: quasi-Newton on it (:class:`_ElasticQuasiNewton`),
        Newton on the consistent tangent if that fails. Else a SNES (Newton) solve."""
        what = f"dynamic step at t = {self.t + float(self.dt.value):.6g} s"
        try:
            if self._affine is not None:
                return self.problem.checked_ksp(self._affine.solve(), what)
            if self._quasi is not None:
                its = self._quasi.solve()
                if its is not None:
                    self.last_solve = {"iterations": its, "fallback": False}
                    return self.problem.checked(self._quasi.nlp, what)
                self.fallbacks += 1
                quasi = self._quasi.nlp.solver
                self.last_solve = {"quasi_iterations": quasi.getIterationNumber(),
                                   "quasi_reason": int(quasi.getConvergedReason()), "fallback": True}
                if self._newton is None:
                    self._newton = self._newton_problem(prefix=self._prefix + "newton_")
                self._newton.solve()
                self.last_solve["iterations"] = self._newton.solver.getIterationNumber()
                return self.problem.checked(self._newton, what)
            self._snes.solve()
            self.last_solve = {"iterations": self._snes.solver.getIterationNumber()}
            return self.problem.checked(self._snes, what)
        except Exception:
            self.problem.w.x.array[:] = self.w_old.x.array
            self.problem.state.restore()
            raise

    def finish(self) -> None:
        """Accept ``w`` as the new state: update velocity, acceleration and time (Newmark)."""
        p, dt = self.params, float(self.dt.value)
        wn, wo, v, a = self.problem.w.x.array, self.w_old.x.array, self.v.x.array, self.a.x.array
        a_new = (wn - wo - dt * v) / (p.beta * dt**2) - (1 - 2 * p.beta) / (2 * p.beta) * a
        v[:] = v + dt * ((1 - p.gamma) * a + p.gamma * a_new)
        a[:] = a_new
        self.t += dt
        # the committed state is the return of the end fields from the last committed state
        # (a UFL model's commit evaluates its state_update at w; a pointwise one's return
        # last ran at the mid-point fields); its tangent is not needed there: a Newton
        # residual evaluates it again
        self._evaluate_points(tangent=False)
        self.problem.state.commit()

    def _evaluate_points(self, tangent: bool = True) -> None:
        """A model returning at the quadrature points: its return at ``w`` (collective)."""
        if self._points_at is not None:
            self.problem.model.evaluate_points(self.problem, tangent=tangent)

    def step(self) -> int:
        """Advance one step; return SNES iterations (raises with the PETSc reason on failure)."""
        self.predict()
        its = self.solve()
        self.finish()
        return its

    def energies(self, weight=None) -> tuple[float, float]:
        """(kinetic, elastic) energy [J] (per unit thickness in 2D), optionally weighted by a
        UFL expression ``weight`` (e.g. an indicator of a region)."""
        return self._energies(weight)


class EnergyForms:
    """The kinetic and stored energy of a problem's model at velocities ``v`` (the model's
    densities integrated), optionally weighted by a UFL expression; the forms compiled once
    a weight (a time stepper's energies)."""

    def __init__(self, problem: ContinuumProblem, v: fem.Function):
        self.problem, self.v = problem, v
        self._forms: dict = {}

    def forms(self, weight=None) -> tuple:
        # keyed by the weight's id, the weight kept with its forms: a weight built for one
        # call (``1 - indicator``) would otherwise be freed and its id given to the next
        key = None if weight is None else id(weight)
        if key not in self._forms:
            p = self.problem
            densities = (p.model.kinetic_energy(p.split(self.v)),
                         p.model.stored_energy(p.split(p.w), p.state.committed))
            self._forms[key] = (weight, tuple(fem.form((e if weight is None else weight * e) * p.dx,
                                                       jit_options=p.jit_options) for e in densities))
        return self._forms[key][1]

    def __call__(self, weight=None) -> tuple[float, float]:
        """(kinetic, stored) energy [J] (per unit thickness in 2D). Collective."""
        comm = self.problem.domain.comm
        return tuple(comm.allreduce(fem.assemble_scalar(f), MPI.SUM) for f in self.forms(weight))


class _ElasticQuasiNewton:
    """The generalized-alpha step of a plastic model by quasi-Newton on its elastic Jacobian
    ``c_m M + (1 - alpha_f) K_elastic`` (:data:`granfe.solvers.ELASTIC_QUASI_NEWTON`). The
    residual is the step's own, so the answer is Newton's to the solver's tolerance; the
    Jacobian does not change with the plastic state, so it is assembled and factorised once,
    again only when dt, a modulus or the Dirichlet conditions change
    (:func:`granfe.solvers.fixed_jacobian`). A step that stays elastic converges in one
    iteration."""

    def __init__(self, problem: ContinuumProblem, nlp):
        self.problem, self.nlp = problem, nlp

    @classmethod
    def build(cls, stepper: GeneralizedAlpha, F, w_mid, a_mid, tangent: bool = True):
        """The quasi-Newton step, or None when the model has no state or no elastic tangent
        (``elastic_work``) or the linear solver is iterative (it would not be factorised).
        ``tangent``: whether the residual ``F`` reads a pointwise model's tangent (False: its
        points are evaluated without it)."""
        problem = stepper.problem
        model, V = problem.model, problem.V
        if not problem.state or not hasattr(model, "elastic_work") or problem.solver_kind == "iterative":
            return None
        dw = ufl.TestFunctions(V)
        F_elastic = problem.weighted(model.inertia_work(problem.split(a_mid), dw)
                                     + model.elastic_work(problem.split(w_mid), dw)) * problem.dx
        J = ufl.derivative(F_elastic, problem.w, ufl.TrialFunction(V))
        # the problem's options (tolerances, the linear solver) over the quasi-Newton's, but
        # not a model's Newton line search: the backtracking one of the pointwise micromorphic
        # model ("bt") measures its sufficient decrease with the elastic Jacobian, which is not
        # the residual's, and failed the reduced plastic pile's second FE step at once
        # (DIVERGED_LINE_SEARCH, then Newton on the 45 x 45 consistent tangent); with the full
        # step it converged in 6 iterations and the steps after took 5-16, as many as with "bt"
        options = {**ELASTIC_QUASI_NEWTON, **problem.petsc_options,
                   "snes_linesearch_type": ELASTIC_QUASI_NEWTON["snes_linesearch_type"]}
        nlp = make_snes_problem(F, problem.w, problem.bcs, stepper._prefix, options, J=J,
                                jit_options=problem.jit_options)
        constants = list(J.constants())
        points_at = stepper._points_at
        fixed_jacobian(nlp, problem.bcs,
                       lambda: (_values(constants), tuple(id(bc) for bc in problem.bcs)),
                       before_residual=None if points_at is None else
                       lambda: model.evaluate_points(problem, points_at, tangent=tangent))
        return cls(problem, nlp)

    def solve(self) -> int | None:
        """Iterations of a converged solve of ``problem.w``, or None (``w`` back where it
        started) if it did not converge."""
        w = self.problem.w.x.array
        start = w.copy()
        self.nlp.solve()
        snes = self.nlp.solver
        if snes.getConvergedReason() > 0 and np.all(np.isfinite(w)):
            return snes.getIterationNumber()
        w[:] = start
        self.problem.w.x.scatter_forward()
        return None


def _values(constants) -> tuple:
    return tuple(np.array(c.value, dtype=float).tobytes() for c in constants)


def _without_zeros(A: PETSc.Mat) -> PETSc.Mat:
    """A copy of the assembled AIJ matrix ``A`` without its stored zeros. The sparsity of a
    mixed space couples every dof of a cell with every other one, but the mass couples only
    equal components (5/6 of its stored entries are zero) and the stiffness leaves 1/3 zero:
    the products cost a fraction of the time and are the same to round-off (a stored zero adds
    nothing; a vectorised kernel may group the remaining terms differently)."""
    indptr, cols, vals = A.getValuesCSR()
    keep = vals != 0.0
    new_ptr = np.concatenate([[0], np.cumsum(keep)])[indptr].astype(PETSc.IntType)
    B = PETSc.Mat().createAIJ(A.getSizes(), csr=(new_ptr, cols[keep].astype(PETSc.IntType), vals[keep]),
                              comm=A.getComm())
    B.assemble()
    return B


class _AffineStep:
    """The generalized-alpha step when its residual is affine in ``w``::

        F(w) = M y1(w) + K y2(w) - L,   y1 = c_m (w - w_old - dt v) + c_a a,
                                        y2 = (1 - alpha_f) w + alpha_f w_old,

    with the mass matrix M, the stiffness K (both without Dirichlet conditions) and the
    load vector L, and ``J = c_m M + (1 - alpha_f) K``. Newton's first iterate from any
    ``w`` is then the solution: insert the Dirichlet values into ``w`` (this is the lifting),
    evaluate F there by two matrix products, zero it on the Dirichlet rows, and subtract
    ``J^-1 F`` (J with the Dirichlet rows and columns replaced by the identity, factorised
    once). That is the SNES solve's result to round-off, without assembling the residual
    form twice per step (the SNES evaluates it at the start and again to test convergence).

    M, K and J are re-assembled (and J refactorised) when a constant of J (dt, moduli,
    density), a value of the model's fixed fields (`ContinuumModel.fixed_fields`) or the
    list of Dirichlet conditions changes; L when a constant in it changes,
    and at every solve if it holds coefficients (functions that may change silently).
    """

    def __init__(self, stepper: GeneralizedAlpha, L, ksp):
        problem, p = stepper.problem, stepper.params
        model, V = problem.model, problem.V
        self.stepper, self.problem, self.ksp = stepper, problem, ksp
        trial, dw = ufl.TrialFunctions(V), ufl.TestFunctions(V)
        m_ufl = problem.weighted(model.inertia_work(trial, dw)) * problem.dx
        k_ufl = problem.weighted(model.internal_work(trial, dw, problem.state.committed)) * problem.dx
        self._m, self._k = (fem.form(m_ufl, jit_options=problem.jit_options),
                            fem.form(k_ufl, jit_options=problem.jit_options))
        self._matrix_constants = list({id(x): x for x in (*m_ufl.constants(), *k_ufl.constants(),
                                                           stepper.dt)}.values())
        self._l_ufl = L if L != 0 else None
        self._l = None if self._l_ufl is None else fem.form(L, jit_options=problem.jit_options)
        self._l_constants = [] if self._l_ufl is None else list(self._l_ufl.constants())
        self._l_varies = self._l_ufl is not None and len(self._l_ufl.coefficients()) > 0
        self._matrix_key = self._l_key = None
        #: "cholesky" or "lu" (:meth:`_symmetric_factor`), once the step is first assembled
        self.factorisation = None
        self._watched = [f for f in model.fixed_fields() if f in set(k_ufl.coefficients()) | set(m_ufl.coefficients())]
        self.M = self.K = self.L = None
        imap = V.dofmap.index_map
        self.n_owned = imap.size_local * V.dofmap.index_map_bs
        self.y1 = self.y2 = self.r = self.dw = None
        self.alpha_f = p.alpha_f
        self.c_a = p.alpha_m - (1 - p.alpha_m) * (1 - 2 * p.beta) / (2 * p.beta)
        self.c_m = lambda dt: (1 - p.alpha_m) / (p.beta * dt**2)

    @classmethod
    def build(cls, stepper: GeneralizedAlpha, F, L):
        """The affine step, or None when the residual is not affine in w (then SNES) or the
        linear solver is not direct (an iterative KSP keeps the Newton control)."""
        from ufl.algorithms import expand_derivatives, extract_coefficients

        problem = stepper.problem
        w = problem.w
        if not problem.model.linear or problem.state:
            return None
        J = expand_derivatives(ufl.derivative(F, w, ufl.TrialFunction(problem.V)))
        # the partition weight is fixed once set (granfe.problem.ContinuumProblem.set_weight);
        # the model's fixed fields are watched (_AffineStep.solve)
        fixed = set() if problem.weight is None else set(extract_coefficients(ufl.as_ufl(problem.weight)))
        fixed |= set(problem.model.fixed_fields())
        if set(J.coefficients()) - fixed:   # J depends on w (or on other functions)
            return None
        if L != 0 and w in L.coefficients():
            return None
        ksp = stepper._snes.solver.getKSP()
        if ksp.getType() != "preonly" or ksp.getPC().getType() not in ("lu", "cholesky", "redundant"):
            return None
        return cls(stepper, L, ksp)

    def _assemble_matrices(self, bcs):
        from dolfinx.fem.petsc import assemble_matrix

        snes = self.stepper._snes
        for name, form in (("M", self._m), ("K", self._k)):
            A = assemble_matrix(form)
            A.assemble()
            if getattr(self, name) is not None:
                getattr(self, name).destroy()
            setattr(self, name, _without_zeros(A))
            A.destroy()
        A = snes.A
        A.zeroEntries()
        assemble_matrix(A, snes.J, bcs, diag=1.0)
        A.assemble()
        self._symmetric_factor(A)
        self.ksp.setOperators(A, A)
        if self.r is None:
            self.y1, self.y2 = self.M.createVecRight(), self.M.createVecRight()
            self.r, self.dw = self.M.createVecLeft(), self.M.createVecLeft()
            self.ky = self.M.createVecLeft()

    def _symmetric_factor(self, A) -> None:
        """Factor J by Cholesky (MUMPS LDL^T) when it is symmetric to round-off, else LU;
        chosen at the first assembly, before the KSP's set-up (a model's J keeps its symmetry
        when its constants change).

        J of a linear model is the Hessian of its energy (plus the mass), symmetric with its
        Dirichlet rows and columns alike; the symmetric factor holds half the entries, and the
        step's triangular solves, bound by reading them from memory, take ~9 % less time
        (the 3D chamber's 10.6k dofs: 8.3 against 9.1 ms; its factorisation 0.56 against
        0.65 s). A non-symmetric J keeps LU."""
        if self.factorisation is not None:
            return
        pc = self.ksp.getPC()
        norm = A.norm(PETSc.NormType.INFINITY)
        want = "cholesky" if norm > 0 and A.isSymmetric(1e-13 * norm) else "lu"
        if pc.getType() == "redundant":   # (its inner KSP reads its options at the set-up)
            PETSc.Options()[f"{self.ksp.getOptionsPrefix() or ''}redundant_pc_type"] = want
        elif pc.getType() != want:
            solver = pc.getFactorSolverType()
            pc.setType(want)
            pc.setFactorSolverType(solver)
        self.factorisation = want

    def _assemble_load(self):
        from dolfinx.fem.petsc import assemble_vector

        if self.L is None:
            self.L = assemble_vector(self._l)
        else:
            with self.L.localForm() as loc:
                loc.set(0.0)
            assemble_vector(self.L, self._l)
        self.L.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)

    def solve(self):
        """Solve the step for ``problem.w``; returns the KSP (to check its reason)."""
        problem, st = self.problem, self.stepper
        bcs = list(problem.bcs)
        key = (_values(self._matrix_constants), tuple(id(bc) for bc in bcs),
               tuple(f.x.array.tobytes() for f in self._watched))
        if key != self._matrix_key or any(a is not b for a, b in zip(bcs, self._bcs, strict=False)):
            self._assemble_matrices(bcs)
            self._matrix_key, self._bcs = key, bcs
            dofs = [bc.dof_indices() for bc in bcs]
            self._fixed = np.unique(np.concatenate([d[:n] for d, n in dofs] + [np.zeros(0, np.int32)]))
        if self._l is not None:
            lkey = _values(self._l_constants)
            if self._l_varies or lkey != self._l_key:
                self._assemble_load()
                self._l_key = lkey
        n, dt = self.n_owned, float(st.dt.value)
        w = problem.w.x.array
        for bc in bcs:                      # the Dirichlet values (owned and ghost entries)
            bc.set(w)
        wn, wo, v, a = w[:n], st.w_old.x.array[:n], st.v.x.array[:n], st.a.x.array[:n]
        self.y1.array[:] = self.c_m(dt) * (wn - wo - dt * v) + self.c_a * a
        self.y2.array[:] = (1 - self.alpha_f) * wn + self.alpha_f * wo
        self.M.mult(self.y1, self.r)
        self.K.mult(self.y2, self.ky)
        self.r.axpy(1.0, self.ky)
        if self.L is not None:
            self.r.axpy(-1.0, self.L)
        self.r.array[self._fixed] = 0.0
        self.ksp.solve(self.r, self.dw)
        w[:n] -= self.dw.array_r
        problem.w.x.scatter_forward()
        return self.ksp
