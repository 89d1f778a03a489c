"""PETSc SNES set-up: default options, convergence checks, rigid-body near-nullspace.

Direct (MUMPS LU) is the default; ``ONE_LU_PER_STEP`` reuses a load step's first LU for its
later Newton iterations (plastic paths); ``ELASTIC_QUASI_NEWTON`` with :func:`fixed_jacobian`
steps a plastic model on its elastic Jacobian, factorised once (dynamic steps); ``ITERATIVE``
is CG + smoothed-aggregation AMG (GAMG) with the micropolar rigid-body modes as
near-nullspace, for large 3D problems.
Any PETSc option can be overridden per problem.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from petsc4py import PETSc

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import NonlinearProblem

__all__ = [
    "DIRECT",
    "REDUNDANT",
    "ITERATIVE",
    "ONE_LU_PER_STEP",
    "ELASTIC_QUASI_NEWTON",
    "SolveDidNotConverge",
    "make_snes_problem",
    "fixed_jacobian",
    "check_converged",
    "check_ksp_converged",
    "rigid_body_modes",
    "rigid_modes_nullspace",
]

DIRECT = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "none",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-14,
    "snes_max_it": 25,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}

# direct, each rank factorising the whole system with sequential MUMPS (PCREDUNDANT): the same
# bits run to run on the same rank count. Parallel MUMPS schedules its factorisation
# dynamically, so its round-off differs from run to run; coupled to chaotic grains that
# round-off grows tenfold per FE step into a different trajectory (issue 14, measured: two
# 2-rank runs of scenes/cpt_2d.toml first differed at FE step 15; with this, not in 100)
REDUNDANT = {
    "pc_type": "redundant",
    "redundant_pc_type": "lu",
    "redundant_pc_factor_mat_solver_type": "mumps",
}

# one LU factorisation per load step: the tangent of the step's first Newton iteration
# preconditions GMRES on the assembled tangent of the later iterations (Newton's iterates are
# unchanged); pays once the factorisation dominates a plastic step (benchmarks/plastic_cost.py:
# 4.3x -> 2.9x the elastic path at 10k dofs, 4.3x -> 4.0x at 2.6k). With a direct solver only,
# and not "redundant": PCREDUNDANT refactorises at every iteration despite the lag (the dynamic
# case of benchmarks/plastic_cost.py: 25 LU factorisations for 25 Newton iterations).
ONE_LU_PER_STEP = {
    "snes_lag_preconditioner": 100,
    "ksp_type": "gmres",
    "ksp_rtol": 1e-8,
    "ksp_gmres_restart": 100,
    "ksp_max_it": 200,
}

# quasi-Newton (L-BFGS) whose first inverse is a fixed Jacobian: with the elastic Jacobian of
# a plastic model, factorised once (fixed_jacobian), an iteration costs a residual and a pair of
# triangular solves, where Newton assembles the consistent tangent and refactorises it; an
# elastic step converges in one. The 3D chamber's dynamic step (benchmarks/plastic_cost.py,
# 11.5k / 21.7k dofs, 45 % of the points yielding): 9-14 iterations, 0.39 / 1.06 s against
# Newton's 4.2 / 11.0 s (4-5 iterations). L-BFGS although a non-associated tangent is not symmetric:
# Broyden's updates diverged on the 3D chamber step of benchmarks/plastic_cost.py (tried once,
# not recorded), Anderson over the fixed-Jacobian iteration took fewer iterations but two
# residuals each. No step-length test: at a linear rate the steps are small long before the
# residual is.
ELASTIC_QUASI_NEWTON = {
    "snes_type": "qn",
    "snes_qn_type": "lbfgs",
    "snes_qn_scale_type": "jacobian",
    "snes_qn_m": 20,
    "snes_linesearch_type": "basic",
    "snes_stol": 0.0,
}

ITERATIVE = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "none",
    "snes_rtol": 1e-9,
    "snes_atol": 1e-14,
    "snes_max_it": 25,
    "ksp_type": "cg",
    "ksp_rtol": 1e-10,
    "ksp_max_it": 2000,
    "pc_type": "gamg",
    "pc_gamg_type": "agg",
    "pc_gamg_threshold": 0.01,
    "mg_levels_ksp_type": "chebyshev",
    "mg_levels_pc_type": "jacobi",
}

_SNES_REASONS = {
    getattr(PETSc.SNES.ConvergedReason, n): n
    for n in dir(PETSc.SNES.ConvergedReason)
    if not n.startswith("_")
}
_KSP_REASONS = {
    getattr(PETSc.KSP.ConvergedReason, n): n
    for n in dir(PETSc.KSP.ConvergedReason)
    if not n.startswith("_")
}


class SolveDidNotConverge(RuntimeError):
    """A SNES solve ended with a negative converged reason; the message names it."""

    def __init__(self, message: str, reason: int):
        super().__init__(message)
        self.reason = reason


def make_snes_problem(F, w: fem.Function, bcs, prefix: str, options: dict | None,
                      J=None, near_nullspace: PETSc.NullSpace | None = None,
                      jit_options: dict | None = None) -> NonlinearProblem:
    """A ``NonlinearProblem`` with ``DIRECT`` options updated by ``options``."""
    opts = dict(DIRECT)
    if options:
        opts.update(options)
    if opts.get("pc_type") not in ("lu", "cholesky"):
        opts.pop("pc_factor_mat_solver_type", None)
    problem = NonlinearProblem(F, w, bcs=bcs, J=J, petsc_options_prefix=prefix, petsc_options=opts,
                               jit_options=jit_options)
    if near_nullspace is not None:
        problem.A.setNearNullSpace(near_nullspace)
    return problem


def fixed_jacobian(problem: NonlinearProblem, bcs, key, before_residual=None) -> None:
    """Assemble the Jacobian of ``problem`` (its ``J`` form, rows and columns of the Dirichlet
    conditions ``bcs`` replaced by the identity) only when ``key()`` changes, e.g. the values
    of the form's constants and the conditions: a matrix left untouched keeps its
    factorisation (PETSc sets a preconditioner up again only when its operator changed).
    ``before_residual()``: called at every residual once the unknown holds its iterate (a
    model returning at the quadrature points fills its state there; the residual's
    coefficients are then packed whole every time).

    The residual lifts the Dirichlet values as dolfinx's does, ``b + K (g - x)`` over their
    columns, but by a product with ``K``, the same form assembled without the conditions
    (kept with the Jacobian): dolfinx lifts with the form, one element matrix per cell with a
    constrained dof, on the 3D chamber as long as the residual's own assembly."""
    from dolfinx.fem.petsc import assemble_matrix, assemble_vector, assign, set_bc

    last, K = [None], assemble_matrix(problem.J)
    K.assemble()
    jump = problem.b.duplicate()                    # ghosted, as set_bc writes ghosts too

    def jacobian(snes, x, J, P):
        k = key()
        if k != last[0]:
            for A, conditions in ((J, bcs), (K, [])):
                A.zeroEntries()
                assemble_matrix(A, problem.J, conditions, diag=1.0)
                A.assemble()
            last[0] = k

    coefficients = _Coefficients(problem.F, problem.u)

    def residual(snes, x, b):
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        assign(x, problem.u)
        if before_residual is not None:
            before_residual()
        with b.localForm() as loc:
            loc.set(0.0)
        whole = before_residual is not None or snes.getIterationNumber() == 0
        assemble_vector(b, problem.F, coeffs=coefficients.packed(whole))
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        jump.set(0.0)
        set_bc(jump, bcs, x0=x)                     # g - x on the Dirichlet dofs, else 0
        K.multAdd(jump, b, b)
        set_bc(b, bcs, x0=x, alpha=-1.0)            # x - g on their rows
        b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

    problem.solver.setJacobian(jacobian, problem.A, problem.A)
    problem.solver.setFunction(residual, problem.b)


class _Coefficients:
    """The residual's coefficients packed cell by cell (dolfinx packs them all at every
    assembly: a third of a Drucker-Prager dynamic residual's time), packed again whole at a
    solve's first iteration (the state and the last step's fields change between solves)
    and otherwise only the unknown's columns. Only where a gather of the unknown's cell dofs
    is its packed form (no dof transformations; checked against dolfinx's packing)."""

    def __init__(self, F, u):
        self.F, self.u, self.coeffs = F, u, None
        names = [id(c) for c in F._cpp_object.coefficients]
        sizes = [c.function_space.dofmap.dof_layout.num_dofs * c.function_space.dofmap.bs
                 for c in F._cpp_object.coefficients]
        keys = list(fem.pack_coefficients(F))
        self.usable = (id(u._cpp_object) in names and len(keys) == 1 and keys[0][0] == fem.IntegralType.cell
                       and not u.function_space.element.needs_dof_transformations)
        if self.usable:
            i = names.index(id(u._cpp_object))
            self.key, self.columns = keys[0], slice(sum(sizes[:i]), sum(sizes[:i + 1]))
            cells = F._cpp_object.domains(*self.key)
            self.dofs = u.function_space.dofmap.list[cells]

    def packed(self, whole: bool):
        if not self.usable:
            return None
        if whole or self.coeffs is None:
            self.coeffs = fem.pack_coefficients(self.F)
            gathered = self._gather()
            self.usable = np.array_equal(self.coeffs[self.key][:, self.columns], gathered)
        else:
            self.coeffs[self.key][:, self.columns] = self._gather()
        return self.coeffs

    def _gather(self):
        return self.u.x.array[self.dofs].reshape(len(self.dofs), -1)


def check_converged(problem: NonlinearProblem, what: str) -> int:
    """Return SNES iterations, or raise :class:`SolveDidNotConverge` naming the PETSc reason."""
    snes = problem.solver
    reason = snes.getConvergedReason()
    if reason > 0:
        return snes.getIterationNumber()
    ksp_reason = snes.getKSP().getConvergedReason()
    raise SolveDidNotConverge(
        f"{what}: SNES did not converge, reason {_SNES_REASONS.get(reason, '?')} ({reason}) "
        f"after {snes.getIterationNumber()} iterations, |F| = {snes.getFunctionNorm():.3e}; "
        f"last linear solve: {_KSP_REASONS.get(ksp_reason, '?')} ({ksp_reason})",
        reason,
    )


def check_ksp_converged(ksp: PETSc.KSP, what: str) -> int:
    """Return 1 (one linear solve), or raise :class:`SolveDidNotConverge` naming the KSP reason
    (e.g. a failed factorisation)."""
    reason = ksp.getConvergedReason()
    if reason > 0:
        return 1
    raise SolveDidNotConverge(
        f"{what}: linear solve failed, reason {_KSP_REASONS.get(reason, '?')} ({reason}); "
        f"preconditioner: {ksp.getPC().getFailedReason()}",
        reason,
    )


def rigid_modes_nullspace(V: fem.FunctionSpace, modes) -> PETSc.NullSpace:
    """Orthonormalised rigid modes of a model's mixed space as a PETSc nullspace.

    ``modes``: per mode one callable ``x -> values`` per field, or None for a zero field
    (:meth:`granfe.models.base.ContinuumModel.rigid_modes`). Used as the AMG near-nullspace.
    """
    vecs = []
    for mode in modes:
        f = fem.Function(V)
        for i, fn in enumerate(mode):
            if fn is not None:
                f.sub(i).interpolate(fn)
        vecs.append(f.x.petsc_vec.copy())
    for i, v in enumerate(vecs):  # modified Gram-Schmidt
        for u in vecs[:i]:
            v.axpy(-v.dot(u), u)
        v.normalize()
    return PETSc.NullSpace().create(vectors=vecs, comm=V.mesh.comm)


def rigid_body_modes(V: fem.FunctionSpace) -> PETSc.NullSpace:
    """The micropolar rigid-body modes of a mixed (u, phi) space: translations
    (u = e_k, phi = 0) and rotations (u = e_k x x, phi = e_k), 3 in 2D, 6 in 3D."""
    from granfe.models.micropolar import Micropolar

    return rigid_modes_nullspace(V, Micropolar.rigid_modes(V.mesh.geometry.dim))
