"""The mechanics' step of a staggered Biot continuum whose pore fluid is solved elsewhere: a
skeleton model in total stress, with the pore pressure's increment over the step as a field.

A Biot continuum solved in two steps per time step: the mechanics with the pressure as the
flow last left it plus the increment the step's own volume change and drainage make, then
the flow (another solver: e.g. one pressure field over grains and continuum) with the
skeleton's volume change over the step as its source. This model is the first of the two.
Fields: the skeleton's, and ``p`` [Pa], the pressure's increment over the step (P1), with::

    skeleton's internal work - s (p_f + p) div du                    (total stress; alpha = 1)
    - (S p + s div(u - u_n)) dp - tau kappa grad(p_f + p) . grad dp = 0    (the fluid's mass)

``p_f`` the flow's last pressure and ``u_n`` the displacement at the step's start (their
terms are loads, the caller's: :meth:`granfe.problem.ContinuumProblem.volume_work`), ``S``
[1/Pa] the fluid's storage (``n beta_f``: :attr:`storage`), ``kappa = k / mu_f`` its mobility
(:attr:`mobility`), ``tau`` [s] the time from the step's start to where the stepper
evaluates its forces (:attr:`step`: ``(1 - alpha_f) dt`` for the generalised-alpha method,
whose internal forces are at ``t_{n+1-alpha_f}``), ``s`` the skeleton's share of the fluid's
force and volume change (:attr:`share`, 1; a field where another model, e.g. grains, carries
the rest). The model's own work is linear and homogeneous in its fields, so a linear
skeleton keeps one factorisation for the run.

With ``kappa = 0`` this is the undrained split (Armero & Simo 1992; Kim, Tchelepi & Juanes
2011): stable, first order, and far off at practical steps (Terzaghi's column at 200 steps
to T = 1: settlement -20 % at T = 0.1, -4 % at T = 1). With the continuum's own flow in the
step the increment is the flow's backward-Euler answer and the split's error is the flow's
(0.44 %, tests/granfe/test_undrained_split.py). Either way the increment's equation has the
flow's own mass term (the same mass matrix as a P1 flow): a predictor of another
discretisation (``-s div(u - u_n) / S`` cell by cell) differs from the flow's answer in the
modes P1 pressures do not resolve; the next step released the difference, and in 2D (P1 u,
P1 p) that split blew up within ten steps in the undrained limit.
"""

from __future__ import annotations

import ufl
from dolfinx import default_scalar_type, fem

from granfe.models.base import ContinuumModel, Field

__all__ = ["UndrainedSplit"]


class UndrainedSplit(ContinuumModel):
    """A linear skeleton model (without state) and the pressure increment ``p`` of the
    module docstring.

    Args:
        skeleton: the skeleton's model (e.g. :class:`~granfe.models.micropolar.Micropolar`);
            its first field is the displacement.
        storage: the fluid's storage ``S = n beta_f`` [1/Pa] > 0.
        mobility: ``kappa = k / mu_f`` [m^2 / (Pa s)] >= 0 (0: the undrained split).

    After the problem is built (:meth:`bind`) the forms' constants are :attr:`storage`,
    :attr:`mobility` and :attr:`step` (``tau`` [s], 0 until the caller sets it), and
    :attr:`share` (a P1 function, 1) holds ``s``."""

    name = "undrained_split"
    linear = True

    def __init__(self, skeleton: ContinuumModel, storage: float, mobility: float = 0.0):
        if not skeleton.linear:
            raise ValueError(f"UndrainedSplit: the skeleton must be linear (an elastic model), got "
                             f"{skeleton.name}")
        if not (isinstance(storage, int | float) and storage > 0 and storage < float("inf")):
            raise ValueError(f"UndrainedSplit: storage must be a positive number of 1/Pa (n beta_f), "
                             f"got {storage!r}")
        if not (isinstance(mobility, int | float) and 0 <= mobility < float("inf")):
            raise ValueError(f"UndrainedSplit: mobility must be a number >= 0 of m^2/(Pa s) (k / mu_f), "
                             f"got {mobility!r}")
        self.skeleton = skeleton
        self._storage0, self._mobility0 = float(storage), float(mobility)
        self.storage = self.mobility = self.step = self.share = None
        super().__init__(skeleton.material)

    # ---- set-up ---------------------------------------------------------------------
    def bind(self, domain) -> None:
        self.skeleton.bind(domain)
        if self.skeleton.state_variables(domain.geometry.dim):
            raise ValueError(f"UndrainedSplit: the skeleton {self.skeleton.name} keeps a state; "
                             "an elastic one so far")
        self.gdim, self.constants = self.skeleton.gdim, self.skeleton.constants
        self.storage = fem.Constant(domain, default_scalar_type(self._storage0))
        self.mobility = fem.Constant(domain, default_scalar_type(self._mobility0))
        self.step = fem.Constant(domain, default_scalar_type(0.0))
        self.share = fem.Function(fem.functionspace(domain, ("Lagrange", 1)), name="skeleton_share")
        self.share.x.array[:] = 1.0

    def dimensions(self) -> tuple[int, ...]:
        return self.skeleton.dimensions()

    def fixed_fields(self) -> tuple:
        return (self.share,)   # (set once by a coupling: the step factorised once)

    def update(self, material) -> None:
        self.skeleton.update(material)
        self.material = material

    def fields(self, gdim: int) -> tuple[Field, ...]:
        return (*self.skeleton.fields(gdim), Field("p", (), ("p",), 1))

    def constant_values(self, material) -> dict[str, float]:
        return self.skeleton.constant_values(material)

    def state_variables(self, gdim: int) -> dict:
        return {}

    # ---- physics --------------------------------------------------------------------
    def internal_work(self, w, dw, state):
        *ws, p = w
        *dws, dp = dw
        s = self.share
        return (self.skeleton.internal_work(tuple(ws), tuple(dws), state) - s * p * ufl.div(dws[0])
                - (self.storage * p + s * ufl.div(ws[0])) * dp
                - self.step * self.mobility * ufl.inner(ufl.grad(p), ufl.grad(dp)))

    def inertia_work(self, a, dw):
        return self.skeleton.inertia_work(tuple(a[:-1]), tuple(dw[:-1]))

    def kinetic_energy(self, v):
        return self.skeleton.kinetic_energy(tuple(v[:-1]))

    def stored_energy(self, w, state):
        return self.skeleton.stored_energy(tuple(w[:-1]), state)

    def stresses(self, w, state):
        return self.skeleton.stresses(tuple(w[:-1]), state)

    def rigid_modes(self, gdim: int):
        return [(*mode, None) for mode in self.skeleton.rigid_modes(gdim)]

    def plot_fields(self, w, state):
        return {**self.skeleton.plot_fields(tuple(w[:-1]), state), "p_increment": w[-1]}
