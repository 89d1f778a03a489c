"""PETSc SNES set-up: default options, convergence checks, rigid-body near-nullspace.

Direct (MUMPS LU) is the default; ``ITERATIVE`` is CG + smoothed-aggregation AMG
(GAMG) with the micropolar rigid-body modes as near-nullspace, for large 3D problems.
Any PETSc option can be overridden per problem.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401

import numpy as np
from dolfinx import fem
from dolfinx.fem.petsc import NonlinearProblem
from petsc4py import PETSc

__all__ = [
    "DIRECT",
    "ITERATIVE",
    "SolveDidNotConverge",
    "make_snes_problem",
    "check_converged",
    "check_ksp_converged",
    "rigid_body_modes",
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
                      J=None, near_nullspace: PETSc.NullSpace | None = None) -> NonlinearProblem:
    """A ``NonlinearProblem`` with ``DIRECT`` options updated by ``options``."""
    opts = dict(DIRECT)
    if options:
        opts.update(options)
    if opts.get("pc_type") not in ("lu", "cholesky"):
        opts.pop("pc_factor_mat_solver_type", None)
    problem = NonlinearProblem(F, w, bcs=bcs, J=J, petsc_options_prefix=prefix, petsc_options=opts)
    if near_nullspace is not None:
        problem.A.setNearNullSpace(near_nullspace)
    return problem


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


def rigid_body_modes(V: fem.FunctionSpace) -> PETSc.NullSpace:
    """Orthonormalised micropolar rigid-body modes of the mixed (u, phi) space.

    Translations (u = e_k, phi = 0) and rotations (u = e_k x x, phi = e_k): 3 in 2D
    (phi_z only), 6 in 3D. Used as the AMG near-nullspace.
    """
    gdim = V.mesh.geometry.dim
    modes = []

    def mode(u_of_x, phi_value):
        f = fem.Function(V)
        f.sub(0).interpolate(u_of_x)
        if phi_value is not None:
            f.sub(1).interpolate(lambda x: np.tile(np.reshape(phi_value, (-1, 1)), x.shape[1])
                                 if np.ndim(phi_value) else np.full(x.shape[1], float(phi_value)))
        return f

    for k in range(gdim):
        modes.append(mode(lambda x, k=k: np.vstack([np.full(x.shape[1], float(i == k))
                                                     for i in range(gdim)]), None))
    if gdim == 2:
        modes.append(mode(lambda x: np.vstack([-x[1], x[0]]), 1.0))
    else:
        for k in range(3):
            e = np.eye(3)[k]
            modes.append(mode(lambda x, e=e: np.cross(e[:, None], x[:3], axis=0), e))
    vecs = [f.x.petsc_vec.copy() for f in modes]
    for i, v in enumerate(vecs):  # modified Gram-Schmidt
        for u in vecs[:i]:
            v.axpy(-v.dot(u), u)
        v.normalize()
    return PETSc.NullSpace().create(vectors=vecs, comm=V.mesh.comm)
