"""Finite-strain three-level micromorphic Drucker-Prager elastoplasticity on a mesh (after
Regueiro 2010; 3D and 2D plane strain): :class:`MicromorphicFiniteDruckerPrager`, the UFL /
dolfinx side.

The material point (the multiplicative splits ``F = F^e F^p``, ``chi = chi^e chi^p`` and the
plastic micro-gradient ``G^p``, the cones on the conjugates of the three levels' plastic
rates, the return mapping and its consistent tangent) is
:func:`~granfe.models.micromorphic_finite_return.finite_return`, whose module docstring holds
the equations. The model runs it at the quadrature points and assembles the residual from
the nominal stresses and the tangent it returns (class docstring). Checked by the tests
(tests/granfe/test_micromorphic_finite_plasticity.py).

Plane strain (2D) is the 3D point with the out-of-plane motion held: ``F_33 = chi_33 = 1``,
``u_3,I = u_I,3 = 0``, ``phi_i3 = phi_3i = 0`` and no gradient along 3. The 2D fields are
embedded in the kernel's 3D measures with those entries zero, so the point returns its full
3D state (the out-of-plane stresses of plane strain included), and the residual's test
measures, zero there too, keep the in-plane equations.
"""

from __future__ import annotations

from typing import ClassVar

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import fem

from granfe.models.micromorphic import Micromorphic, strain_energy_density
from granfe.models.micromorphic_drucker_prager import MicromorphicDruckerPragerMaterial
from granfe.models.micromorphic_finite import MicromorphicFiniteStrain
from granfe.models.micromorphic_finite_return import finite_return, kernel_tables
from granfe.models.micromorphic_return import LEVEL_COUNT

__all__ = ["MicromorphicFiniteDruckerPrager"]


class MicromorphicFiniteDruckerPrager(MicromorphicFiniteStrain):
    """Finite-strain micromorphic Drucker-Prager (:mod:`granfe.models.micromorphic_finite_return`)
    on a mesh, 3D and 2D plane strain (the module docstring), with the return at the quadrature points
    (:func:`~granfe.models.micromorphic_finite_return.finite_return`), as
    :class:`~granfe.models.micromorphic_iterative.MicromorphicDruckerPragerIterative` does
    in small strain: before every residual assembly :meth:`evaluate_points` fills the
    nominal stresses ``y = [P, Q, R]`` and their consistent tangent at the points, and the
    residual is their expansion about the evaluated fields::

        (y + tangent (x(w) - measures)) . x(dw),     x = [grad u, phi, grad phi] (45),

    exact where the points were just evaluated (``P : grad du + Q : dphi + R : grad dphi``,
    the first variation of psi at the plastic state of the step's end).

    Quadrature-point state: ``plastic_deformation`` ``F^p - I`` and
    ``plastic_micro_deformation`` ``chi^p - I`` (3 x 3, zero at the start),
    ``plastic_micro_gradient`` ``G^p`` (3 x 3 x 3), ``equivalent_plastic_strain`` (5),
    ``yielding`` (3: macro, micro, any slice, in the last evaluation), and the cache of the
    last evaluation ``stress``, ``measures`` (45) and ``tangent`` (45 x 45). Cost: ~5-10 ms a
    yielding point with its tangent (differences of the return's equations), ~0.6 ms an
    elastic one (0.03 ms without the tangent).
    """

    name = "micromorphic_finite_drucker_prager"
    linear = False
    material_type = MicromorphicDruckerPragerMaterial
    solver_options: ClassVar[dict] = {"snes_max_it": 50, "snes_divergence_tolerance": 1e300,
                                      "snes_linesearch_type": "bt"}

    def __init__(self, material):
        super().__init__(material)
        self._measures: dict[int, tuple] = {}

    def dimensions(self) -> tuple[int, ...]:
        return (2, 3)

    def constant_values(self, material):
        self.tables = kernel_tables(material)
        return Micromorphic.constant_values(self, material.elastic)

    def state_variables(self, gdim):
        return {"plastic_deformation": (3, 3), "plastic_micro_deformation": (3, 3),
                "plastic_micro_gradient": (3, 3, 3), "equivalent_plastic_strain": (LEVEL_COUNT,),
                "yielding": (3,), "stress": (45,), "measures": (45,), "tangent": (45, 45)}

    def state_update(self, w, state):
        """None for every variable: :meth:`evaluate_points` writes the trial state."""
        return {name: None for name in self.state_variables(3)}

    def _embedded(self, w):
        """``(grad u, phi, grad phi)`` as 3D UFL tensors (2D: zero out of plane)."""
        u, phi = self._split(w)
        d = ufl.shape(u)[0]
        gu, gp = ufl.grad(u), ufl.grad(phi)
        if d == 3:
            return gu, phi, gp

        def inside(*ix):
            return all(i < d for i in ix)

        r = range(3)
        return (ufl.as_matrix([[gu[i, j] if inside(i, j) else 0.0 for j in r] for i in r]),
                ufl.as_matrix([[phi[i, j] if inside(i, j) else 0.0 for j in r] for i in r]),
                ufl.as_tensor([[[gp[i, j, k] if inside(i, j, k) else 0.0 for k in r] for j in r] for i in r]))

    def measures(self, w):
        """``x(w) = [grad u, phi, grad phi]`` (row-major: ``u_i,J``, ``phi_iJ``,
        ``phi_iJ,K``; 3D, in 2D with the out-of-plane entries zero)."""
        gu, phi, gp = self._embedded(w)
        r = range(3)
        return ufl.as_vector([gu[i, j] for i in r for j in r] + [phi[i, j] for i in r for j in r]
                             + [gp[i, j, k] for i in r for j in r for k in r])

    def _expansion(self, w, state):
        return state["stress"] + ufl.dot(state["tangent"], self.measures(w) - state["measures"])

    def internal_work(self, w, dw, state):
        return ufl.dot(self._expansion(w, state), self.measures(dw))

    def point_work(self, w, dw, state):
        """``stress . x(dw)``: the residual at fields the points were just evaluated at."""
        return ufl.dot(state["stress"], self.measures(dw))

    def elastic_work(self, w, dw):
        """The elastic model's virtual work (from no plastic deformation)."""
        return MicromorphicFiniteStrain.internal_work(self, w, dw, {})

    def stresses(self, w, state):
        """The first Piola-Kirchhoff ``P``, PK2 ``S = F^-1 P`` and Cauchy ``P F^T / J`` of
        the expansion (2D: their in-plane parts; F is block diagonal with ``F_33 = 1``)."""
        y = self._expansion(w, state)
        u = self._split(w)[0]
        d = ufl.shape(u)[0]
        P = ufl.as_matrix([[y[3 * i + j] for j in range(d)] for i in range(d)])
        F = ufl.Identity(d) + ufl.grad(u)
        return {"first_piola": P, "pk2": ufl.inv(F) * P, "cauchy": P * F.T / ufl.det(F)}

    def stored_energy(self, w, state):
        """The stored energy psi of the elastic measures at the committed plastic state (UFL)."""
        grad_u, phi, grad_phi = self._embedded(w)
        eye = ufl.Identity(3)
        F, chi = eye + grad_u, eye + phi
        Fpi = ufl.inv(eye + state["plastic_deformation"])
        chipi = ufl.inv(eye + state["plastic_micro_deformation"])
        Gp = state["plastic_micro_gradient"]
        Ce = Fpi.T * F.T * F * Fpi
        Psie = Fpi.T * F.T * chi * chipi
        a, b, c, i, j, k, d = ufl.indices(7)
        X = ufl.as_tensor(Fpi[i, a] * F[d, i] * grad_phi[d, j, k] - Psie[a, i] * Gp[i, j, k],
                          (a, j, k))
        Ge = ufl.as_tensor(X[a, j, k] * chipi[j, b] * Fpi[k, c], (a, b, c))
        return strain_energy_density((Ce - eye) / 2, Psie - eye, Ge, self.constants)

    def evaluate_points(self, problem, fields=None, tangent: bool = True) -> None:
        """The return at every quadrature point of this rank's cells for the current
        ``problem.w`` (``fields``: a UFL expression of it to evaluate instead): the trial
        plastic state, and the stress and tangent the residual expands about (committed and
        trial alike: a cache, not history). A failed return makes the residual NaN (SNES
        fails, the problem restores its last good state). Collective."""
        state = problem.state
        fields = problem.w if fields is None else fields
        if id(fields) not in self._measures:
            Q = state.committed["stress"].function_space
            self._measures[id(fields)] = (fields, fem.Expression(
                self.measures(problem.split(fields)), Q.element.interpolation_points,
                jit_options=problem.jit_options))
        domain = problem.domain
        cells = np.arange(domain.topology.index_map(domain.topology.dim).size_local, dtype=np.int32)
        x = self._measures[id(fields)][1].eval(domain, cells).reshape(-1, 45)
        npts = x.shape[0]

        def dofs(name):
            d = state.committed[name].function_space.dofmap.list[: len(cells)].ravel()
            return slice(0, d.size) if np.array_equal(d, np.arange(d.size)) else d

        def owned(name, *shape):
            return state.committed[name].x.array.reshape(-1, int(np.prod(shape)))[dofs(name)] \
                .reshape(npts, *shape)

        old = {"Fp": np.eye(3) + owned("plastic_deformation", 3, 3),
               "chip": np.eye(3) + owned("plastic_micro_deformation", 3, 3),
               "Gp": owned("plastic_micro_gradient", 3, 3, 3),
               "eq": owned("equivalent_plastic_strain", LEVEL_COUNT)}
        _, _, _, new, info = finite_return(
            x[:, :9].reshape(-1, 3, 3), np.eye(3) + x[:, 9:18].reshape(-1, 3, 3),
            x[:, 18:].reshape(-1, 3, 3, 3), old, self.material, self.tables, tangent)
        y = info["nominal"]
        if domain.comm.allreduce(int(np.sum(info["passes"] < 0))):
            y[:] = np.nan
        flags = info["yielding"]
        trial = {"plastic_deformation": new["Fp"] - np.eye(3),
                 "plastic_micro_deformation": new["chip"] - np.eye(3),
                 "plastic_micro_gradient": new["Gp"], "equivalent_plastic_strain": new["eq"],
                 "yielding": np.column_stack([flags[:, 0], flags[:, 1], flags[:, 2:].max(axis=1)])}
        cache = {"stress": y, "measures": x}
        if tangent:
            cache["tangent"] = info["tangent"]
        for name, values in list(trial.items()) + list(cache.items()):
            rows = np.ascontiguousarray(values).reshape(npts, -1)
            f = state.trial[name]
            f.x.array.reshape(-1, rows.shape[1])[dofs(name)] = rows
            f.x.scatter_forward()
            if name in cache:
                state.committed[name].x.array[:] = f.x.array
