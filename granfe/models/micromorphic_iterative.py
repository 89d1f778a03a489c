"""Three-level micromorphic Drucker-Prager plasticity for any moduli: the return mapping at the
quadrature points (:mod:`granfe.models.micromorphic_return`, numba) instead of in UFL.

The same physics as :class:`~granfe.models.micromorphic_drucker_prager.MicromorphicDruckerPrager`
(fields, measures, cones, flow rule, apex, state), whose closed-form returns need decoupled
levels (``D = 0``, ``C = tau7 I``). With coupled moduli the levels return together by Newton
(one small dense system per point), which UFL cannot express, so this model fills the
stress and the consistent tangent at the quadrature points before every residual assembly
(:meth:`evaluate_points`, called by the problem's SNES residual) and writes the residual as
their first-order expansion about the evaluation point, as
:class:`~granfe.models.quadrature_stress.QuadratureStress` does::

    y(w) = stress + tangent (x(w) - measures),     x(w) = [eps, E, G] (in-plane components),

exact where the points were just evaluated (``measures = x(w)``), with Newton's Jacobian
``tangent`` from ``ufl.derivative``. Quadrature-point state: the plastic parts and
equivalent plastic strains of the closed-form model (the same names and shapes, so
checkpoints read alike), plus the filled ``stress``, ``measures`` and ``tangent`` (the
linearisation: written to the committed and trial state alike, it is a cache of the last
evaluation, not history).

Cost: one Newton per yielding point (45-component stress, up to 44 unknowns) and a 45 x 45
(3D) or 16 x 16 (2D) tangent per point; elastic points cost one matrix-vector product.
Quasi-static solves (``ContinuumProblem.solve``) and the explicit stepper evaluate the
points at the current fields; the implicit dynamic stepper (generalised-alpha) at its
residual's mid-point fields, and at the step's end fields before it commits the state (the
closed-form model's commit: the return of the end fields from the committed state).
"""

from __future__ import annotations

from typing import ClassVar

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import fem

from granfe.models.micromorphic import Micromorphic, strains
from granfe.models.micromorphic_drucker_prager import LEVELS, MicromorphicDruckerPragerMaterial
from granfe.models.micromorphic_return import LEVEL_COUNT, NX, point_return, stiffness

__all__ = ["MicromorphicDruckerPragerIterative", "measure_indices"]


def measure_indices(gdim: int) -> np.ndarray:
    """Positions in the 45-component measure vector of the components a ``gdim`` problem has
    (plane strain: the in-plane ones, 16; 3D: all 45), in the order of :meth:`measures`."""
    r = range(gdim)
    eps = [3 * i + j for i in r for j in r]
    E = [9 + 3 * i + j for i in r for j in r]
    G = [18 + 9 * M + 3 * k + l for M in r for k in r for l in r]
    return np.array(eps + E + G, dtype=np.int64)


class MicromorphicDruckerPragerIterative(Micromorphic):
    """Micromorphic Drucker-Prager with the return at the quadrature points (module
    docstring); any moduli the elastic material admits."""

    name = "micromorphic_drucker_prager_iterative"
    linear = False
    material_type = MicromorphicDruckerPragerMaterial
    # a step starts from a converged state whose residual is only the boundary increment:
    # no divergence test; a backtracking line search (every residual it tries evaluates the
    # points at its fields): full Newton steps flip a point's active set back and forth on a
    # finer mesh with coupled moduli (the 3D platens, 4 x 4 x 8 cells: |F| alternating
    # 0.17 / 0.31 for 50 iterations; with "bt" 3-10 iterations a step). Newton's only: the
    # dynamic stepper's elastic-Jacobian quasi-Newton keeps its full step (granfe.dynamics)
    solver_options: ClassVar[dict] = {"snes_max_it": 50, "snes_divergence_tolerance": 1e300,
                                      "snes_linesearch_type": "bt"}

    def __init__(self, material):
        super().__init__(material)
        # the measures' expression per fields evaluated at (w, or a stepper's mid-point
        # fields), each kept with the UFL fields it was compiled for
        self._measures: dict[int, tuple] = {}

    def constant_values(self, material):
        values = super().constant_values(material.elastic)
        # the kernel's tables, rebuilt on every update: unlike the closed-form model's forms,
        # nothing compiled depends on which levels are plastic
        self._tables(material)             # after bind: gdim is known (the slices it has)
        return values

    def _tables(self, material) -> None:
        """The kernel's constants: K, and per level (A, B, k0, H) and whether it has a cone."""
        self.K = stiffness(material.elastic)
        self.cones = np.zeros((LEVEL_COUNT, 4))
        self.has_cone = np.zeros(LEVEL_COUNT, dtype=bool)
        for i in range(LEVEL_COUNT):
            cone = getattr(material, LEVELS[min(i, 2)])
            if cone is None or i >= 2 + (self.gdim or 3):
                continue
            self.cones[i] = (*cone.constants, cone.hardening)
            self.has_cone[i] = True

    def state_variables(self, gdim):
        n = len(measure_indices(gdim))
        return {"plastic_strain": (3, 3), "plastic_micro_strain": (3, 3),
                "plastic_micro_gradient": (gdim, 3, 3),
                "equivalent_plastic_strain": (2 + gdim,), "yielding": (3,),
                "stress": (n,), "measures": (n,), "tangent": (n, n)}

    def state_update(self, w, state):
        """None for every variable: :meth:`evaluate_points` writes the trial state."""
        return {name: None for name in self.state_variables(ufl.shape(w[0])[0])}

    # ---- UFL ------------------------------------------------------------------------
    def measures(self, w):
        """``x(w)``: the components of eps, E and G (:func:`measure_indices`' order)."""
        u, phi = self._split(w)
        gdim = ufl.shape(u)[0]
        eps, E, G = strains(u, phi)
        r = range(gdim)
        return ufl.as_vector([eps[i, j] for i in r for j in r] + [E[i, j] for i in r for j in r]
                             + [G[k, l, M] for M in r for k in r for l in r])

    def _stress(self, w, state):
        return state["stress"] + ufl.dot(state["tangent"], self.measures(w) - state["measures"])

    def _blocks(self, y, gdim):
        """``S``, ``T`` (gdim x gdim) and ``m`` (gdim^3) of a stress vector (UFL)."""
        r, n2 = range(gdim), gdim * gdim
        S = ufl.as_matrix([[y[gdim * i + j] for j in r] for i in r])
        T = ufl.as_matrix([[y[n2 + gdim * i + j] for j in r] for i in r])
        m = ufl.as_tensor([[[y[2 * n2 + n2 * M + gdim * k + l] for M in r] for l in r] for k in r])
        return S, T, m

    def internal_work(self, w, dw, state):
        return ufl.dot(self._stress(w, state), self.measures(dw))

    def point_work(self, w, dw, state):
        """The virtual work of the stress of the last evaluation, ``stress . x(dw)``: the
        residual at fields the points were just evaluated at (:meth:`internal_work` there to
        round-off: its expansion's other term is ``tangent (x(w) - measures)``, zero) without
        the tangent, which a step on a fixed (elastic) Jacobian does not need: its residual
        then packs 45 values a point, not 2115 (:meth:`evaluate_points` ``tangent=False``)."""
        return ufl.dot(state["stress"], self.measures(dw))

    def elastic_work(self, w, dw):
        """The elastic model's virtual work (the explicit stepper's stability limit)."""
        return Micromorphic.internal_work(self, w, dw, {})

    def stresses(self, w, state):
        gdim = ufl.shape(w[0])[0]
        S, T, m = self._blocks(self._stress(w, state), gdim)
        return {"sigma": S + T.T, "micro_stress": S + T + T.T, "higher_order_stress": m,
                "relative_stress": T}

    def stored_energy(self, w, state):
        """The energy of the elastic parts of the three measures (the plastic parts of the
        committed state), plane strain embedded in 3D as the kernel sees it."""
        from granfe.models.micromorphic import strain_energy_density
        from granfe.models.micromorphic_drucker_prager import _to3

        u, phi = self._split(w)
        gdim = ufl.shape(u)[0]
        eps, E, G = strains(u, phi)
        Gp = state["plastic_micro_gradient"]

        def g_elastic(k, l, M):
            total = G[k, l, M] if max(k, l, M) < gdim else 0.0
            return total - (Gp[M, k, l] if M < gdim else 0.0)

        G_e = ufl.as_tensor([[[g_elastic(k, l, M) for M in range(3)] for l in range(3)]
                             for k in range(3)])
        return strain_energy_density(_to3(eps, gdim) - state["plastic_strain"],
                                     _to3(E, gdim) - state["plastic_micro_strain"], G_e,
                                     self.constants)

    # ---- the points -----------------------------------------------------------------
    def evaluate_points(self, problem, fields=None, tangent: bool = True) -> None:
        """The return at every quadrature point of this rank's cells for the current
        ``problem.w`` (``fields``: a UFL expression of it whose residual is assembled instead,
        e.g. generalized-alpha's mid-point fields): trial plastic state, and the stress and
        tangent the residual expands about (committed and trial alike). Ghost cells from
        their owners. Collective.

        ``tangent=False``: the stress and measures only, the tangent left as it was (a
        residual of :meth:`point_work`, which has none, or a commit): in 3D the tangent is
        2025 values a point, written twice, and it was most of this call's time and of the
        residual's coefficient packing (the elastic-Jacobian quasi-Newton step never reads
        it). The expansion ``stress + tangent (x(w) - measures)`` then still holds at the
        evaluated fields, where ``x(w) = measures`` to round-off."""
        state, gdim = problem.state, problem.gdim
        fields = problem.w if fields is None else fields
        if id(fields) not in self._measures:
            Q = state.committed["stress"].function_space
            self._measures[id(fields)] = (fields, fem.Expression(
                self.measures(problem.split(fields)), Q.element.interpolation_points,
                jit_options=problem.jit_options))
        domain = problem.domain
        cells = np.arange(domain.topology.index_map(domain.topology.dim).size_local, dtype=np.int32)
        idx = measure_indices(gdim)
        n_idx = len(idx)
        full = n_idx == NX                 # 3D: every component, no gather or scatter of them
        x_in = self._measures[id(fields)][1].eval(domain, cells).reshape(-1, n_idx)
        npts = x_in.shape[0]
        if full:
            x = x_in
        else:
            x = np.zeros((npts, NX))
            x[:, idx] = x_in

        def dofs(name):
            d = state.committed[name].function_space.dofmap.list[: len(cells)].ravel()
            # the owned cells' points in order (a quadrature space's usual numbering): a slice
            return slice(0, d.size) if np.array_equal(d, np.arange(d.size)) else d

        def owned(name, size):
            return state.committed[name].x.array.reshape(-1, size)[dofs(name)]

        xp_old = np.zeros((npts, NX))
        xp_old[:, :9] = owned("plastic_strain", 9)
        xp_old[:, 9:18] = owned("plastic_micro_strain", 9)
        xp_old[:, 18: 18 + 9 * gdim] = owned("plastic_micro_gradient", 9 * gdim)
        eq_old = np.zeros((npts, LEVEL_COUNT))
        eq_old[:, : 2 + gdim] = owned("equivalent_plastic_strain", 2 + gdim)
        y, C, xp, eq, flags, failed = point_return(x, xp_old, eq_old, self.K, self.cones,
                                                   self.has_cone, tangent)
        failed = domain.comm.allreduce(failed)
        if failed:
            # a NaN residual makes SNES fail and the problem restore the last good state
            y[:] = np.nan
        yielding = np.column_stack([flags[:, 0], flags[:, 1], flags[:, 2:].max(axis=1)])
        trial = {"plastic_strain": xp[:, :9], "plastic_micro_strain": xp[:, 9:18],
                 "plastic_micro_gradient": xp[:, 18: 18 + 9 * gdim],
                 "equivalent_plastic_strain": eq[:, : 2 + gdim], "yielding": yielding}
        cache = {"stress": y if full else y[:, idx], "measures": x_in}
        if tangent:
            cache["tangent"] = C if full else C[:, idx][:, :, idx]
        for name, values in list(trial.items()) + list(cache.items()):
            rows = np.ascontiguousarray(values).reshape(npts, -1)
            f = state.trial[name]
            f.x.array.reshape(-1, rows.shape[1])[dofs(name)] = rows
            f.x.scatter_forward()
            if name in cache:              # the same values: a copy of the whole array
                state.committed[name].x.array[:] = f.x.array
