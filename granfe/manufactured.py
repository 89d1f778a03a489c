"""Manufactured solutions of micropolar elasticity for convergence studies (tests, benchmarks).

The body force and body couple come from the strong form of the same energy the solver
uses: ``f = -div sigma``, ``l = -div m + e_ijk sigma_ij`` (2D: ``sigma_01 - sigma_10``).
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem

from granfe.forms import stresses
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

__all__ = ["MMS_MATERIAL", "exact_fields", "manufactured_problem", "errors", "rates"]

MMS_MATERIAL = MicropolarMaterial(lam=2.0, mu=1.0, kappa=0.5, alpha=0.3, beta=0.2, gamma=0.6)


def everywhere(x):
    return np.full(x.shape[1], True)


def exact_fields(domain):
    """Smooth manufactured (u, phi) as UFL expressions and as numpy callables."""
    x = ufl.SpatialCoordinate(domain)
    gdim = domain.geometry.dim
    if gdim == 2:
        u = ufl.as_vector([ufl.sin(np.pi * x[0]) * ufl.cos(x[1]), x[0] * x[1] ** 2])
        phi = ufl.cos(x[0] + 2 * x[1])
        u_np = lambda p: np.vstack([np.sin(np.pi * p[0]) * np.cos(p[1]), p[0] * p[1] ** 2])  # noqa: E731
        phi_np = lambda p: np.cos(p[0] + 2 * p[1])  # noqa: E731
    else:
        u = ufl.as_vector([ufl.sin(x[0]) * x[2], ufl.cos(x[1] + x[2]), x[0] * x[1]])
        phi = ufl.as_vector([ufl.sin(x[1]), x[0] * x[2], ufl.cos(x[0])])
        u_np = lambda p: np.vstack([np.sin(p[0]) * p[2], np.cos(p[1] + p[2]), p[0] * p[1]])  # noqa: E731
        phi_np = lambda p: np.vstack([np.sin(p[1]), p[0] * p[2], np.cos(p[0])])  # noqa: E731
    return u, phi, u_np, phi_np


def manufactured_problem(domain, degree, material=MMS_MATERIAL, **kwargs):
    """Problem whose exact solution is :func:`exact_fields` (body force and couple from the
    strong form)."""
    u_ex, phi_ex, u_np, phi_np = exact_fields(domain)
    c_problem = MicropolarProblem(domain, material, degree=degree,
                                  **{"prefix": f"mms{id(domain)}_", **kwargs})
    sigma, m = stresses(u_ex, phi_ex, c_problem.constants)
    gdim = domain.geometry.dim
    if gdim == 2:
        axial = sigma[0, 1] - sigma[1, 0]
    else:
        axial = ufl.as_vector([sigma[1, 2] - sigma[2, 1], sigma[2, 0] - sigma[0, 2],
                               sigma[0, 1] - sigma[1, 0]])
    c_problem.body_force(-ufl.div(sigma))
    c_problem.body_couple(-ufl.div(m) + axial)
    c_problem.fix(everywhere, "u", u_np)
    c_problem.fix(everywhere, "phi", phi_np)
    return c_problem, u_ex, phi_ex


def errors(problem, u_ex, phi_ex):
    """L2 and H1 seminorm errors of u and phi against the exact fields."""
    u, phi = problem.w.split()
    comm = problem.domain.comm
    dx = ufl.dx(metadata={"quadrature_degree": 8})

    def norm(e):
        return np.sqrt(comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(e, e) * dx)), MPI.SUM))

    return {"u_L2": norm(u - u_ex), "u_H1": norm(ufl.grad(u - u_ex)),
            "phi_L2": norm(phi - phi_ex), "phi_H1": norm(ufl.grad(phi - phi_ex))}


def rates(meshes, degree):
    """Convergence rates between the last two meshes, and every mesh's errors."""
    errs = []
    for domain in meshes:
        problem, u_ex, phi_ex = manufactured_problem(domain, degree)
        problem.solve()
        errs.append(errors(problem, u_ex, phi_ex))
    return {k: np.log2(errs[-2][k] / errs[-1][k]) for k in errs[0]}, errs


