"""Saturated coupled penetration (CPTu): one Darcy pore pressure over the whole chamber,
driven by the window's grains and by the continuum, acting on the free grains.

The pressure ``p`` (the deviation from hydrostatic) is one P1 field on the continuum's mesh,
continuous across the overlap by construction, solved every ``fluid.every`` DEM steps by
backward Euler (`coupling.pore_fluid.DarcyFlow`, seed 003 eq. 5.4-5.5):

    (n beta_f + (1 - b)(1 - w) / K) dp/dt + div v - div((k / mu_f) grad p) = 0,

    v = w v_grains + (1 - w) v_FE,    n = w n_grains + (1 - w) n_0,

with ``w`` the grains' weight on the mesh's nodes: 1 inside the window down to the
coupling's prescribed nodes (a handshake inside its edge), falling linearly to 0 where a
node's support would reach past the grains (an element inside the ghost band's outer edge),
0 in the continuum; ``b`` = 1 on the nodes where w = 0 (the continuum alone), 0 in the
overlap. Inside, the source is the grains' volumetric change (their volume-weighted mean
velocity by the FE basis at their centroids, the penetrator's solid counted as a grain
moving at its velocity) and the grains feel the seepage force ``-grad p`` by their weight w.
Between fluid steps that force would lag the grains: with a fluid step every DEM step the
implicit drag of `dem.drag.GroupDrag` holds the lag off; with one every few DEM steps
(cheaper) every DEM step between adds the last step's response to the grains'
displacement since it and the drainage of its pressure over the time since
(:meth:`ChamberFlow.interval_forces`: the fluid's stiffness and Darcy resistance, one
back-substitution with the step's factors). On one rank the DEM applies that response
itself in its fused step loop (`dem.response.LinearResponse` from
:meth:`ChamberFlow.interval_response`) and the fluid steps run between DEM steps
(`dem.Simulation.step`'s ``pause``); on several, or under an exchange's hook, a hook
applies it (the Python step loop). Either way it may come once in s DEM steps, s times
its middle step's force (multiple time stepping's impulse; ``fluid.response_every``, s
chosen below the response's stiffest mode: :meth:`SaturatedPenetration._stride`).

The continuum (``fluid.continuum = "biot"``, the default) is a Biot continuum in total
stress beyond the overlap: its FE step is `granfe.models.undrained_split.UndrainedSplit`
(the skeleton, and the pressure's increment over the step with the continuum's own flow,
from the last fluid step's pressure; the skeleton pushed by ``-b grad(p)``), and the fluid
steps after it take the continuum's displacement change over the step as its source ``v_FE``.
Undrained it deforms nearly isochorically, drained as the dry continuum
(tests/coupling/test_cptu.py); 2D only so far (3D: :data:`BIOT_3D`). In the overlap
(0 < w < 1, b = 0) its mechanics stay drained:
the grains take the seepage force by w, the continuum's share is dropped, and its volume
change enters with the fixed-stress storage ``(1 - w) / K`` (K its bulk modulus, plane
strain in 2D). With the Biot continuum there too (b = 1 - w) the coupled chamber blew up
undrained (V = 32, the 2D CPTu scene): the continuum's undrained resistance to the grains'
own volume changes at the prescribed nodes came back through the ghosts.
``fluid.continuum = "drained"``: the dry continuum everywhere, its volume change the source
with storage ``(1 - w) / K`` (the fixed-stress estimate of a Biot continuum whose total mean
stress the dry run gives: undrained ``p = K eps_v``), kept to compare.

The penetrator is solid to the fluid: points filling its section (spacing half a grain
radius) carry its area at its velocity into the solid fraction and the mean velocity,
and the permeability inside it falls to ``k (1 - c)`` (c its area fraction, floored at a
thousandth). Its share of ``-int grad p dx`` is the pore pressure's force on it: the
excess-pressure part of the cone's total resistance, ``q_t = q_c + q_u`` (q_c the grains'
contacts, the effective part). The top (the free surface) is drained, every other side
undrained. Readings per FE step: ``u1`` (the face, mid-height, a grain radius out), ``u2``
(the shoulder just above the cone, a grain radius out, CPTu's standard position) and
``u_max`` the largest excess pressure, from the solve at the step's start.

Resolution: the pressure is unresolved at the grains' scale (a window node's support holds
~10-20 grains) and the cone is a few elements wide, so the discrete divergence of the solid
velocity misses the isochoric flow round the cone by O(v / R) over an element: an excess
pressure of order ``(mu_f / k) (v / R) h^2``, the mesh's, not the soil's. It grows with V
and falls with h (here faster than h^2): in the loose scene at V ~ 1, u2 read 13.9 / 1.9 /
0.6 kPa with 8 / 6 / 5 mm elements (R = 10 mm; means over depths 20-30 mm, one packing,
the fast run of demos/2d/cptu_coupled.py, measured while the water above the grains was
soil, below). Readings are credible where that error is below
the effective stress (here V up to ~1 with 5 mm elements); at V ~ 30 it dominates.

Above the grains the water is free: a window that settles below its ghosts' top (the loose
scenes/cptu_2d.toml by 19 mm, the dense cpt_2d.toml by 3 mm) has water over its grains
inside the mesh, and a node whose support holds less than half the window's median solid
fraction (COVERED) takes up to FREE_WATER times the soil's permeability (1 / its cover).
Before this the layer was soil of the scene's k, and it made most of the loose scene's u2:
the cone starts in it, so u2 read pressure before the shoulder reached the grains, and the
drainage up through it was the soil's (0.66 kPa at V ~ 1 over 20-30 mm of push; with the
free layer 0.23 / 0.05 / -0.01 kPa over 22-45 mm in three packings). The shoulder is a
grain radius into the grains after ~38 mm of push in the loose scene
(demos/2d/cptu_coupled.py pushes 45 mm).

2D and 3D (the penetrator's body filled with points, u1 / u2 at four azimuths, q_u over
pi R^2; the continuum drained), one rank or several (the grains replicated, the fluid's sums
reduced as in DarcyFlow).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem
from dolfinx.fem.petsc import apply_lifting, assemble_matrix, assemble_vector
from scipy import sparse

from coupling.apps.penetration.coupled import RHO_INF, CoupledPenetration
from coupling.apps.penetration.fluid import BIOT_3D, FluidParameters
from coupling.apps.penetration.parameters import VERTICAL
from coupling.apps.penetration.penetrators import tip_height
from coupling.locate import locate_owned, owner_ranks, relocate
from coupling.pore_fluid import DarcyFlow, GrainSpace, PoreFluidParameters
from dem.drag import group_means
from dem.ldl import LDL
from dem.response import LinearResponse, applies
from dem.state import FREE
from granfe.dynamics import AlphaParameters
from granfe.models.undrained_split import UndrainedSplit

__all__ = ["ChamberFlow", "SaturatedPenetration", "FluidParameters"]

#: the penetrator's permeability over the soil's at full solid cover
CONE_PERMEABILITY = 1e-3
#: the permeability of free water over the soil's, where a window's node holds no grains
#: (water above a window that settled below its ghosts' top): high enough that the layer
#: drains as free water would next to the soil (measured: x 1000 brought the loose scene's u2
#: with the shoulder still in the layer from 0.66 to 0.004 kPa; the layer's own k no longer
#: matters past that)
FREE_WATER = 1e3
#: a node counts as fully in the grains once its solid fraction reaches this share of the
#: window's median: the packing's own scatter (~10 % a node) then leaves k untouched, and
#: only nodes less than half covered (the water layer, the surface's top row) see free water
COVERED = 0.5
#: the space of the porosity and solid velocity: P1, each node averaging the grains of its
#: support (~20 grains; a window element holds ~3). Measured on the loose window pushed at
#: V = 29: the pressures with DG0 cells were 3-5x those with P1 (the cells' velocity means
#: are noisier), and DG0 with a fluid step every 10 DEM steps at water's compressibility
#: swung the tip pressure by +-100 kPa from one FE step to the next
POROSITY_SPACE = "P1"


def bulk_modulus(material, dim: int) -> float:
    """Bulk modulus [Pa] of a micropolar material: ``lam + G`` in plane strain (dim 2),
    ``lam + 2 G / 3`` in 3D; G = mu + kappa / 2 its classical shear modulus."""
    G = material.mu + 0.5 * material.kappa
    return material.lam + (G if dim == 2 else 2.0 * G / 3.0)


def constrained_modulus(material) -> float:
    """Constrained (oedometric) modulus ``lam + 2 G`` [Pa] (2D and 3D)."""
    return material.lam + 2 * material.mu + material.kappa


def radial_directions(dim: int) -> np.ndarray:
    """Unit vectors (k, 3) across the penetrator's axis where its readings are taken: both
    sides of the 2D section (x), four azimuths in 3D (x and y)."""
    if dim == 2:
        return np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    return np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])


class ChamberFlow(DarcyFlow):
    """The pore fluid of a :class:`SaturatedPenetration`: a :class:`~coupling.pore_fluid.
    DarcyFlow` on the continuum's mesh whose porosity and solid velocity are the grains'
    and the penetrator's inside the window, blended into the continuum's over the overlap
    (the module docstring). Build it after the continuum (it reads the stepper's velocity).
    """

    def __init__(self, cpt: CoupledPenetration, fluid: FluidParameters):
        prm = cpt.prm
        self.cpt, self.fluid_prm = cpt, fluid
        #: the space dimension and the penetrator's (vertical) axis
        self.gdim, self.ax = prm.dim, VERTICAL[prm.dim]
        params = PoreFluidParameters(viscosity=fluid.viscosity, compressibility=fluid.compressibility,
                                     density=fluid.density, permeability=fluid.permeability,
                                     porosity_space=POROSITY_SPACE, porosity_min=0.02, porosity_max=0.98,
                                     # a fluid step every DEM step: its lag held off by the
                                     # implicit drag; every few: by interval_forces, whose
                                     # flow response the drag would count again
                                     implicit_drag="all" if fluid.every == 1 else "none")
        problem = cpt.problem
        super().__init__(problem.domain, cpt.sim, params, facet_tags=problem.facet_tags,
                         tag_names=problem.tag_names, particles=cpt.n_grains)
        self.drained("top")
        rows, f = cpt.sim.external_force()   # a chamber's surcharge on its top grains: kept
        if len(rows):                        # (the DEM holds one set of external forces)
            self.extra_force = np.zeros((cpt.sim.p.n, 3))
            self.extra_force[rows] = f
        domain, gdim = self.domain, self.gdim
        self.weight = fem.Function(self.Vn, name="grain_weight")
        self.weight.x.array[:] = self._grain_weight(self.Vn.tabulate_dof_coordinates()[:, :gdim])
        self.cone_fraction = fem.Function(self.Vn, name="cone_fraction")
        #: the grains' cover of each node, 1 in the packing and the continuum, 0 in free
        #: water (:meth:`permeability`)
        self.cover = fem.Function(self.Vn, name="grain_cover")
        self.cover.x.array[:] = 1.0
        self.fe_velocity = fem.Function(self.Vv, name="continuum_velocity")
        self._k = fem.Constant(domain, default_scalar_type(fluid.permeability))
        #: the penetrator's speed [m/s] the fluid sees (0 while the window saturates)
        self.cone_speed = prm.velocity
        self.K = bulk_modulus(cpt.material_fe, gdim)
        self.M = constrained_modulus(cpt.material_fe)
        self.skeleton_storage = (1.0 - self.weight) / self.K
        #: continuum = "biot": 1 on the nodes where the continuum alone is the skeleton (w = 0),
        #: 0 in the overlap; the continuum is Biot's there, its own step answering its volume
        #: change, and stays drained in the overlap (the fixed-stress storage kept there). The
        #: continuum's own share field (`UndrainedSplit.share`): one mask for both
        self.biot = None
        if fluid.continuum == "biot":
            self.biot = cpt.problem.model.share
            if not np.array_equal(self.biot.function_space.dofmap.list, self.Vn.dofmap.list):
                raise RuntimeError("the continuum's share space does not number the fluid's dofs alike")
            self.biot.x.array[:] = self.weight.x.array == 0.0
            self.skeleton_storage = (1.0 - self.weight) * (1.0 - self.biot) / self.K
        self._cone = _Tracked(domain, self.Vn.ufl_element(), self._maps, self._tree)
        if not np.array_equal(self._cone.space.V.dofmap.list, self.Vn.dofmap.list):
            raise RuntimeError("the penetrator's space does not number the grains' dofs alike")
        self._probes = _Tracked(domain, self.Vp.ufl_element(), self._maps, self._tree)
        self._cone_template, self._cone_area = self._cone_points()   # (area: volume in 3D)
        self.cone_force = np.zeros(3)   #: the pore pressure's force on the penetrator [N/m in 2D, N in 3D]
        w = self.weight.x.array
        solid = self._work("solid", self.Vn).x.array
        owned = self.Vn.dofmap.index_map.size_local
        inner = w[:owned] >= 1.0
        #: the continuum's porosity: the mean over the fully weighted (owned) nodes, water above
        #: a window that settled below the ghosts' top included (an upper bound; it enters
        #: only the continuum's storage n beta_f, next to its (1 - w) / K)
        self.n0 = float(1.0 - domain.comm.allreduce(float(solid[:owned][inner].sum()))
                        / domain.comm.allreduce(float(self.lumped_mass[:owned][inner].sum())))
        #: the median solid fraction of the window's nodes that hold grains (the cover's scale)
        fraction = solid[:owned][inner] / self.lumped_mass[:owned][inner]
        fraction = np.concatenate(domain.comm.allgather(fraction[fraction > 0]))
        self.packed = float(np.median(fraction)) if fraction.size else 1.0
        self._cone_sums = (np.zeros_like(w), np.zeros((len(w), gdim)))
        self._source_matrix = None   # int u . grad q dx (Vv -> Vp), for interval_forces
        self._serial = None          # interval_forces' scipy products on one rank
        self._ldl = None             # the step's factors on one rank (:meth:`_linear_solve`)
        self.response = None         # interval_response's (one rank)
        self._x_last = None   # the grains' positions at the last fluid step
        self._rate = None     # (n, 3) their displacement rate over it [m/s]
        self._step_dt = None
        self._fe_u_velocity = None

    # ---- where the grains count ------------------------------------------------------------
    def _grain_weight(self, x: np.ndarray) -> np.ndarray:
        """The grains' weight w (m,) at points x (m, gdim): 1 at signed distance -handshake
        from the window (the coupling's prescribed nodes), 0 an element inside the ghost
        band's outer edge, linear between (a node's P1 porosity averages its support, an
        element about it)."""
        prm = self.cpt.prm
        h = prm.element_size_window
        d0 = -prm.handshake * h
        d1 = prm.ghost_width * 2 * prm.radius - h
        if not d1 > d0:
            raise ValueError(f"the overlap has no room for the fluid's blend: window.handshake "
                             f"({prm.handshake} elements) and window.ghost_width ({prm.ghost_width} "
                             f"diameters) leave {d1 - d0:.3g} m")
        d = self.cpt.regions.window.signed_distance(x)
        return np.clip((d1 - d) / (d1 - d0), 0.0, 1.0)

    def _cone_points(self):
        """Points (k, 3) filling the penetrator (its section in 2D, its body in 3D; its tip at
        the origin: the clump's placement is added per solve) on a grid of half a grain
        radius, and the area (2D, m^2) or volume (3D, m^3) each carries: in 2D a grid cell's
        (their sum within 1.6 % of the section's area in the scenes), in 3D the body's volume
        over their count (a cone of 2.5 grain radii fills its grid's cells to 3.5 %)."""
        prm = self.cpt.prm
        R, h_cone = prm.cone_radius, tip_height(prm)
        s = 0.5 * prm.radius
        top = h_cone + prm.depth + 2 * R
        across = np.arange(-R + s / 2, R, s)
        up = np.arange(s / 2, top, s)
        if self.gdim == 2:
            X, Y = np.meshgrid(across, up)
            inside = Y >= np.abs(X) * h_cone / R
            return np.column_stack([X[inside], Y[inside], np.zeros(inside.sum())]), s * s
        X, Y, Z = np.meshgrid(across, across, up, indexing="ij")
        r = np.hypot(X, Y)
        inside = (r <= R) & (Z >= r * h_cone / R)
        volume = np.pi * R**2 * (top - h_cone + h_cone / 3)   # (the shaft, and the cone's third)
        return np.column_stack([X[inside], Y[inside], Z[inside]]), volume / inside.sum()

    def cone_tip(self) -> np.ndarray:
        """(3,) the cone's apex now [m], from the clump's disks where the DEM has them (also
        inside a sub-cycle; the apex disk is ``rc / sin(apex / 2)`` above the apex,
        :func:`~coupling.apps.penetration.penetrators.cone_clump`)."""
        cpt, prm = self.cpt, self.cpt.prm
        ax = VERTICAL[prm.dim]
        pen = cpt.sim.p.x[cpt.pen_index]
        r_pen = float(cpt.sim.p.radius[cpt.pen_index[0]])
        tip = np.zeros(3)
        tip[ax] = pen[:, ax].min() - r_pen / np.sin(np.radians(prm.apex_deg) / 2)
        for c in range(prm.dim):   # (the axis across: x in 2D, x and y in 3D)
            if c != ax:
                tip[c] = float(np.mean(pen[:, c]))
        return tip

    def _penetrator_sums(self):
        """(S_c, sum of area times velocity) (m,), (m, gdim) of the penetrator's section (2D)
        or body (3D) on Vn (its points above the surface carry nothing)."""
        prm, surface, ax, gdim = self.cpt.prm, self.cpt.surface, self.ax, self.gdim
        x = self._cone_template + self.cone_tip()
        area = np.where(x[:, ax] < surface, self._cone_area, 0.0)
        np.minimum(x[:, ax], surface - 1e-6 * prm.radius, out=x[:, ax])
        S = self._work("cone_solid", self.Vn)
        SV = self._work("cone_momentum", self.Vv)
        mine = self._cone.locate(x[:, :gdim])
        self._cone.space.sum_to(area[mine], S)
        v = np.zeros((len(mine), gdim))
        v[:, ax] = -self.cone_speed
        self._cone.space.sum_to(area[mine, None] * v, SV)
        return S.x.array, SV.x.array.reshape(-1, gdim)

    # ---- grains and continuum -> mesh -----------------------------------------------------
    def positions(self) -> np.ndarray:
        """The grains' centroids, those heaved above the mesh (which ends at the settled
        surface) binned at its top: a heave of a grain or two, which the top cells take."""
        x = super().positions().copy()
        np.minimum(x[:, self.ax], self.cpt.surface - 1e-6 * self.cpt.prm.radius, out=x[:, self.ax])
        return x

    def update_from_grains(self) -> None:
        """Porosity and solid velocity on the mesh: the grains' and the penetrator's, weighted
        by w, and the continuum's (n_0, its velocity) by 1 - w (collective)."""
        super().update_from_grains()
        gdim = self.gdim
        solid = self._work("solid", self.Vn).x.array   # sum_i V_i N_a(x_i): the grains'
        x = self.sim.p.x[:self.particles]
        self._rate = None
        if self._x_last is not None and self._step_dt:
            # the grains' mean velocity over the last fluid step: their displacement over it
            self._rate = np.zeros((self.sim.p.n, 3))
            self._rate[:self.particles] = (x - self._x_last) / self._step_dt
            mine = self._mine
            self._grains.sum_to(self.volume[mine, None] * self._rate[mine, :gdim], self.velocity)
        self._x_last = x.copy()
        momentum = self.velocity.x.array.reshape(-1, gdim)
        if self._rate is None:
            momentum = momentum * solid[:, None]
        Sc, SVc = self._penetrator_sums()
        self._cone_sums = (Sc.copy(), SVc.copy())
        S = solid + Sc
        v_g = np.divide(momentum + SVc, S[:, None], out=np.zeros_like(momentum), where=S[:, None] > 0)
        n_g = 1.0 - S / self.lumped_mass
        w = self.weight.x.array
        if self._fe_u_velocity is None:   # (a view of the stepper's velocity: made once)
            self._fe_u_velocity = self.cpt.stepper.v.sub(0)
        self.fe_velocity.interpolate(self._fe_u_velocity)
        v_c = self.fe_velocity.x.array.reshape(-1, gdim)
        self.porosity.x.array[:] = w * n_g + (1.0 - w) * self.n0
        self._clip_porosity()
        self.velocity.x.array[:] = (w[:, None] * v_g + (1.0 - w[:, None]) * v_c).ravel()
        #: the part of it that is not the grains': the penetrator's and the continuum's
        self._other_velocity = (w[:, None] * np.divide(SVc, S[:, None], out=np.zeros_like(SVc),
                                                       where=S[:, None] > 0)
                                + (1.0 - w[:, None]) * v_c).ravel()
        self.cone_fraction.x.array[:] = np.minimum(Sc / self.lumped_mass, 1.0)
        grains = np.clip(solid / (COVERED * self.packed * self.lumped_mass), 0.0, 1.0)
        self.cover.x.array[:] = w * grains + (1.0 - w)
        solid[:] = S   # the penetrator takes its share of the seepage force: the pressure on it

    # ---- the undrained response between fluid steps ---------------------------------------
    def _interval_set_up(self) -> None:
        """At a fluid step: the grains' displacement's scale ``w / (S dt)`` on the grains'
        space (the source's blend, as in :meth:`update_from_grains`, per unit time; 0 where
        no solid is) and their share of a dof's force. The source matrix ``int u . grad q
        dx`` is the mesh's, assembled once. On one rank the products are scipy's, the
        grains' basis and the two scalings taken into one matrix each way (an interval step
        is then ~5 small products and a back-substitution)."""
        if self._source_matrix is None:
            self._source_matrix = assemble_matrix(fem.form(ufl.inner(
                ufl.TrialFunction(self.Vv), ufl.grad(ufl.TestFunction(self.Vp))) * ufl.dx))
            self._source_matrix.assemble()
            if self.domain.comm.size == 1:
                self._serial = {"source": _scipy(self._source_matrix), "force": _scipy(self._force_matrix)}
            # K p as the step's form less its storage: the same quadrature as the step's
            # (UFL takes one degree for the whole form; K's own estimate is lower)
            a, _ = self._forms()
            storage = self._storage * self.porosity
            if self.skeleton_storage is not None:
                storage = storage + self._inv_dt * self.skeleton_storage
            self._flow_form = fem.form(ufl.action(a, self.p) - storage * self.p
                                       * ufl.TestFunction(self.Vp) * ufl.dx)
        vec = assemble_vector(self._flow_form)        # K p_s, the last pressure's flow
        vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        other = self._work("interval_other", self.Vv)  # the penetrator's and continuum's source
        other.x.array[:] = self._other_velocity
        source = self._source_matrix.createVecLeft()
        self._source_matrix.mult(other.x.petsc_vec, source)
        self._flow_of_last = vec.array_r - source.array_r   # (owned dofs)
        vec.destroy()
        source.destroy()
        S = self._work("solid", self.Vn).x.array      # the grains' and the penetrator's
        scale = np.divide(self.weight.x.array, S * self._step_dt, out=np.zeros_like(S), where=S > 0)
        floor = (1.0 - self.params.porosity_max) * self.lumped_mass
        share = np.maximum(S, floor)
        if self._serial is not None:   # the grains' basis rows, scaled each way
            cols, N = self._grains.rows()
            V = self.volume[self._mine, None]
            self._serial["basis"] = (cols, scale[cols] * N * V, V * N * (self.weight.x.array / share)[cols])
            self._serial.pop("to_source", None)    # (made when interval_forces asks)
        self._displacement_scale, self._share = scale, share

    def interval_forces(self, elapsed: float) -> np.ndarray:
        """(n, 3) [N] the change of the fluid's force on every grain ``elapsed`` [s] = tau
        after the last fluid step (of dt, pressure p_s): the pressure change of a backward-
        Euler step over tau from p_s, ``(M + tau K) dp = A du + tau (s - K p_s)`` (M the
        storage, K the flow, A du the source of the grains' displacement du since the step,
        blended on the mesh as the step's source, s the penetrator's and the continuum's
        source at the step's rates), solved with the step's own factors ``M + dt K`` for
        ``M + tau K``, handed out as the step's seepage force is. At tau = dt it is the
        next step's change (to round-off, with the sources at its rates): exact in the
        undrained limit (the storage's stiffness against a compaction) and for a steady
        drained flow (A du = tau (K p_s - s): the held pressure stands), first order in
        between.

        Held over the interval the fluid's forces lag the grains by a fluid step: at every
        DEM step this brings them the fluid's stiffness and its Darcy resistance, so the
        fluid needs no implicit drag (collective; the same on every rank)."""
        gdim, mine = self.gdim, self._mine
        if len(mine) == self.particles:   # (one rank: all of them, in order; a slice's views)
            mine = slice(0, self.particles)
        moved = self.sim.p.x[mine, :gdim] - self._x_last[mine, :gdim]
        drain = elapsed / self._step_dt   # (the step's system is per unit time: A du / dt)
        b, dp = self._work("interval_source", self.Vp), self._work("interval_dp", self.Vp)
        out = np.zeros((self.sim.p.n, 3))
        ops = self._serial
        if ops is not None:
            if "to_source" not in ops:   # (grain rows i of (m, gdim) arrays ravel to gdim i + c)
                N, two = self._grains.matrix(), sparse.identity(gdim, format="csr")
                V = sparse.diags(self.volume[mine])
                scatter = V @ N.T @ sparse.diags(self.weight.x.array / self._share)
                ops["to_source"] = (ops["source"] @ sparse.kron(
                    sparse.diags(self._displacement_scale) @ N @ V, two)).tocsr()
                ops["to_grains"] = (sparse.kron(scatter, two) @ ops["force"]).tocsr()
            b.x.array[:] = ops["to_source"] @ moved.ravel() - drain * self._flow_of_last
            for bc in self.bcs:                           # (p = 0 at the drained dofs)
                bc.set(b.x.array)
            dp.x.array[:] = self._ldl.solve(b.x.array)    # (the step's factors)
            out[mine, :gdim] = (ops["to_grains"] @ dp.x.array).reshape(-1, gdim)
            return out
        du = self._work("interval_du", self.Vv)
        self._grains.sum_to(self.volume[mine, None] * moved, du)
        # (the step's system is per unit time: its source the velocity du / dt)
        du.x.array.reshape(-1, gdim)[:] *= self._displacement_scale[:, None]
        self._source_matrix.mult(du.x.petsc_vec, b.x.petsc_vec)
        owned = self.Vp.dofmap.index_map.size_local
        b.x.array[:owned] -= drain * self._flow_of_last
        for bc in self.bcs:                               # (p = 0 at the drained dofs)
            bc.set(b.x.petsc_vec.array_w)
        self._problem.solver.solve(b.x.petsc_vec, dp.x.petsc_vec)
        dp.x.scatter_forward()
        F = self._work("interval_force", self.Vv)
        self._force_matrix.mult(dp.x.petsc_vec, F.x.petsc_vec)
        F.x.scatter_forward()
        F.x.array.reshape(-1, gdim)[:] *= (self.weight.x.array / self._share)[:, None]
        out[mine, :gdim] = self.volume[mine, None] * self._grains.at_grains(F)
        if self.domain.comm.size > 1:     # each grain on one rank: an exact sum
            self.domain.comm.Allreduce(MPI.IN_PLACE, out, op=MPI.SUM)
        return out

    def stiffest(self, iterations: int = 40) -> float:
        """The largest frequency omega = sqrt(|lambda|) [rad/s] of ``M^-1 G`` over the free
        grains, G = -d interval_forces / d x (the grains' stiffness of the fluid between its
        steps), by power iteration from a fixed random start about the last fluid step's
        positions; the grains are left where they were. Collective, the same on every rank
        (rank 0's)."""
        p = self.sim.p
        n = self.particles
        free = np.flatnonzero(p.kind[:n] == FREE)
        if not len(free):
            return 0.0
        x = p.x.copy()
        mass = p.mass[free, None]
        scale = 1e-6 * self.d

        gdim = self.gdim

        def force(v):
            p.x[free, :gdim] = self._x_last[free, :gdim] + v
            return self.interval_forces(self.sim.dt)[free, :gdim]

        try:
            base = force(0.0)
            v = np.random.default_rng(0).standard_normal((len(free), gdim))
            lam = 0.0
            for _ in range(iterations):
                v *= scale / np.linalg.norm(v)
                a = -(force(v) - base) / mass
                lam = float(np.linalg.norm(a) / np.linalg.norm(v))
                if lam == 0.0:
                    break
                v = a
        finally:
            p.x[:] = x
        return self.domain.comm.bcast(float(np.sqrt(lam)), root=0)

    def interval_response(self) -> LinearResponse:
        """(one rank) :meth:`interval_forces` of the last fluid step as a
        `dem.response.LinearResponse` (:attr:`response`, updated in place): applied at the
        k-th DEM step after the fluid step it adds ``interval_forces(k dt)`` (to round-off;
        the step's own `dem.ldl.LDL` factors, :meth:`_linear_solve`'s), inside the DEM's
        step loop, the fused one too (a numba pass of two sparse products, the basis rows and
        two substitutions; through a Python hook each DEM step cost more than the step
        itself), once every ``stride`` steps (:meth:`SaturatedPenetration._stride`)."""
        ops = self._serial
        if ops is None:
            raise RuntimeError("interval_response: one rank only (interval_forces is collective)")
        if "kept_source" not in ops:   # (p = 0 at the drained dofs: their rows of A are I)
            keep = np.ones(self._ldl.shape[0])
            for bc in self.bcs:
                keep[bc.dof_indices()[0]] = 0.0
            ops["keep"], ops["kept_source"] = keep, (sparse.diags(keep) @ ops["source"]).tocsr()
        drift = ops["keep"] * self._flow_of_last * (self.sim.dt / self._step_dt)
        rows, x_ref = self._mine, self._x_last[self._mine, :self.gdim]
        # (the mesh's operators and the grains' basis rows: fewer entries than their products;
        # the step's own factors, :meth:`_linear_solve`'s)
        ldl = self._ldl
        args = (rows, x_ref, ops["kept_source"], drift, ldl, ops["force"], ops["basis"])
        if self.response is None:
            self.response = LinearResponse(*args, stride=self.fluid_prm.response_every)
        else:
            self.response.update(*args)
        return self.response

    def _seepage_per_volume(self) -> fem.Function:
        """The grains' share of each dof's seepage force per grain volume, weighted by w: in
        the overlap the grains carry the skeleton by w, the continuum by 1 - w (its share is
        dropped: its mechanics are drained there), and outside the window a grain that strays
        there takes none (it took the whole node's, the continuum's, before)."""
        g = super()._seepage_per_volume()
        g.x.array.reshape(-1, self.gdim)[:] *= self.weight.x.array[:, None]
        return g

    def permeability(self):
        """The permeability ``k (1 - c) / s``: c the penetrator's area fraction (1 - c
        floored at CONE_PERMEABILITY), s the grains' cover (floored at 1 / FREE_WATER: free
        water where a window's node holds no grains)."""
        return (self._k * ufl.max_value(1.0 - self.cone_fraction, CONE_PERMEABILITY)
                / ufl.max_value(self.cover, 1.0 / FREE_WATER))

    def set_permeability(self, k: float) -> None:
        """The soil's permeability k [m^2] from the next solve on (forms and drag)."""
        self.params = replace(self.params, permeability=float(k))
        self._k.value = float(k)

    def solve(self, dt: float | None = None):
        self._step_dt = dt
        return super().solve(dt)

    def _linear_solve(self) -> None:
        """On one rank with fluid steps every few DEM steps: the step's system (assembled as
        dolfinx's LinearProblem does) solved by `dem.ldl.LDL` (M + dt K is symmetric positive
        definite, the Dirichlet rows identity; its pattern analysed once), the factors the
        DEM steps between reuse (:meth:`interval_response`, :meth:`interval_forces`): one
        factorisation a fluid step. Else PETSc's solve (sequential MUMPS on every rank)."""
        if self.domain.comm.size > 1 or self.fluid_prm.every == 1:
            return super()._linear_solve()
        prob = self._problem
        A, b = prob.A, prob.b
        A.zeroEntries()
        assemble_matrix(A, prob.a, bcs=prob.bcs)
        A.assemble()
        with b.localForm() as local:
            local.set(0.0)
        assemble_vector(b, prob.L)
        apply_lifting(b, [prob.a], bcs=[prob.bcs])
        b.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        for bc in prob.bcs:
            bc.set(b.array_w)
        S = _scipy(A)
        if self._ldl is None or not self._ldl.same_pattern(S):
            self._ldl = LDL(S)
        else:
            self._ldl.factor(S)
        self.p.x.array[:] = self._ldl.solve(b.array_r)     # (one rank: every dof owned)

    def apply_forces(self) -> None:
        """The grains' forces and drag (DarcyFlow; the drag about the cell means of the
        displacement rate the fluid saw), and the penetrator's share of ``-int grad p dx``
        (:attr:`cone_force`)."""
        super().apply_forces()
        if self.fluid_prm.every > 1:
            self._interval_set_up()
        if self.drag is not None and self._rate is not None:
            self.drag.u_ref[:] = group_means(self._rate, self.drag.group, self.volume,
                                             len(self.drag.u_ref))
        gdim = self.gdim
        F = self.nodal_force.x.array.reshape(-1, gdim)  # (set by the grains' forces just now)
        floor = (1.0 - self.params.porosity_max) * self.lumped_mass
        share = np.maximum(self._work("solid", self.Vn).x.array, floor)
        f = F * (self._cone_sums[0] / share)[:, None]
        owned = self.Vn.dofmap.index_map.size_local
        self.cone_force[:gdim] = self.domain.comm.allreduce(f[:owned].sum(axis=0))

    # ---- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """This rank's fluid state between FE steps, as arrays (``np.savez``-ready): the
        pressure (local dofs), time, the grains' positions at the last fluid step, the
        porosity scales measured at the set-up (``n0``, ``packed``: from the grains as they
        settled), the other external forces, and where the grains, the penetrator's points
        and the probes were located (their cells: located again from them, a point on a
        cell's edge stays in the same cell, so a restart repeats the run's bits)."""
        d = {"p": self.p.x.array.copy(), "t": float(self.t), "n0": self.n0, "packed": self.packed}
        if self._x_last is not None:
            d["x_last"] = self._x_last.copy()
        if self.extra_force is not None:
            d["extra_force"] = self.extra_force.copy()
        for name, (mine, cells) in self._located().items():
            if mine is not None:
                d[f"{name}.mine"], d[f"{name}.cells"] = np.asarray(mine, np.int64), cells.copy()
        return d

    def _located(self) -> dict:
        return {"grains": (self._mine, self._grains.cells), "cone": (self._cone.mine, self._cone.space.cells),
                "probes": (self._probes.mine, self._probes.space.cells)}

    def load_state(self, d) -> None:
        """Restore a :meth:`state_dict` of the same scene and rank count (ValueError naming
        a field that does not fit)."""
        if d["p"].shape != self.p.x.array.shape:
            raise ValueError(f"checkpoint field fluid p has {d['p'].shape} values, the mesh "
                             f"{self.p.x.array.shape}: different parameters or mesh")
        self.p.x.array[:] = d["p"]
        self.t, self.n0, self.packed = float(d["t"]), float(d["n0"]), float(d["packed"])
        self._x_last = np.array(d["x_last"]) if "x_last" in d else None
        self.extra_force = np.array(d["extra_force"]) if "extra_force" in d else None
        if self._x_last is not None and self._x_last.shape != (self.particles, 3):
            raise ValueError(f"checkpoint field fluid x_last has {self._x_last.shape} rows, the "
                             f"run {self.particles} grains")
        num_cells = self.domain.topology.index_map(self.domain.topology.dim).size_local
        for name, tracker in (("grains", None), ("cone", self._cone), ("probes", self._probes)):
            if f"{name}.mine" not in d:
                continue
            mine, cells = np.asarray(d[f"{name}.mine"], np.int64), np.asarray(d[f"{name}.cells"], np.int32)
            if len(cells) != len(mine) or (len(cells) and cells.max() >= num_cells):
                raise ValueError(f"checkpoint field fluid {name}.cells does not fit this mesh")
            if tracker is None:   # (the grains': DarcyFlow's own)
                self._mine, self._grains.cells = mine, cells
            else:
                tracker.mine, tracker.space.cells = mine, cells

    # ---- readings -------------------------------------------------------------------------
    def readings(self) -> dict:
        """u1, u2 [Pa] (excess pore pressures on the face and at the shoulder, a grain radius
        out, averaged over both sides of the section (2D) or four azimuths (3D); 0 above the
        surface, which is drained), the largest excess pressure, and the pressure's push on
        the cone over its projected area q_u [Pa] (2 R in 2D, pi R^2 in 3D; collective)."""
        prm, cpt, ax, gdim = self.cpt.prm, self.cpt, self.ax, self.gdim
        tip, R, h_cone, r = self.cone_tip(), prm.cone_radius, tip_height(prm), prm.radius
        half = np.radians(prm.apex_deg) / 2
        up = np.eye(3)[ax]
        radial = radial_directions(gdim)   # (the faces' outward normal: cos half out, sin half down)
        face = (R / 2 + r * np.cos(half)) * radial + (h_cone / 2 - r * np.sin(half)) * up
        shoulder = (R + r) * radial + (h_cone + r) * up
        k = len(radial)
        x = (np.vstack([face, shoulder]) + tip)[:, :gdim]
        below = x[:, ax] < cpt.surface      # (the surface is drained: 0 above it)
        np.minimum(x[:, ax], cpt.surface - 1e-6 * r, out=x[:, ax])
        mine = self._probes.locate(x)
        vals = np.zeros(len(x))
        vals[mine] = self._probes.space.at_grains(self.p)[:, 0]
        vals = self.domain.comm.allreduce(vals) * below
        out = {"u1": float(vals[:k].mean()), "u2": float(vals[k:].mean())}
        out["u_max"] = self.domain.comm.allreduce(float(self.p.x.array.max(initial=0.0)), op=MPI.MAX)
        area = 2 * R if gdim == 2 else np.pi * R**2
        out["q_u"] = float(self.cone_force[ax] / area)
        return out


def _scipy(A):
    """A PETSc matrix of one rank as scipy CSR."""
    indptr, indices, values = A.getValuesCSR()
    return sparse.csr_matrix((values, indices, indptr), shape=A.getSize())


class _Tracked:
    """Points moving over a fixed mesh and a space's basis at them: located anew only when
    one of this rank's left its cells (as `DarcyFlow.grains_to_mesh` does for the grains)."""

    def __init__(self, domain, element, maps, tree):
        self.domain, self.maps, self.tree = domain, maps, tree
        self.space = GrainSpace(domain, element)
        self.mine = None

    def locate(self, x: np.ndarray) -> np.ndarray:
        """Evaluate the basis at the points x (m, gdim) this rank owns; returns their indices
        (collective)."""
        comm = self.domain.comm
        if self.mine is not None:
            cells, X, _, lost = relocate(self.domain, x[self.mine], self.space.cells, maps=self.maps,
                                            tree=self.tree)
            if comm.allreduce(int(lost.sum())) == 0:
                self.space.evaluate(cells, X)
                return self.mine
        owners = owner_ranks(self.domain, x)
        self.mine = np.flatnonzero(owners == comm.rank)
        self.space.evaluate(*locate_owned(self.domain, x[self.mine], tree=self.tree))
        return self.mine


class SaturatedPenetration(CoupledPenetration):
    """:class:`~coupling.apps.penetration.coupled.CoupledPenetration` with a pore fluid
    (:class:`ChamberFlow`): after the set-up the window takes its buoyancy for
    ``fluid.saturation_time`` (ghosts and penetrator held, the fluid drained at the
    surface; the grains' reference positions are then taken again: the continuum models the
    increment from the saturated state), then each FE step solves the fluid before its DEM
    sub-cycle and every ``fluid.every`` DEM steps in it; the DEM steps between take the
    implicit drag (every = 1) or the interval's forces (every > 1). The history records add
    u1, u2, u_max, q_u and q_t = q_c + q_u (:meth:`ChamberFlow.readings`). Loose exchange;
    checkpoints hold the fluid's state (:meth:`ChamberFlow.state_dict`) beside the dry run's,
    and a restart from one (``checkpoint``) repeats the run's bits."""

    def __init__(self, prm, fluid: FluidParameters, comm, log=print, checkpoint=None):
        if prm.substeps % fluid.every:
            raise ValueError(f"fluid.every = {fluid.every} DEM steps must divide the FE step's "
                             f"substeps ({prm.substeps})")
        if prm.interface != "loose":
            raise ValueError(f"interface = {prm.interface!r}: a saturated penetration exchanges "
                             "loosely so far (interface = 'loose')")
        self.fluid = fluid
        self.pore_pressure = None   # the continuum's copy of p (continuum = "biot")
        if checkpoint is not None:   # (before the base reads a continuum of other fields)
            self._fluid_file(Path(checkpoint), comm)
        super().__init__(prm, comm, log=log, checkpoint=checkpoint)
        t0 = time.perf_counter()
        self.flow = ChamberFlow(self, fluid)
        if self.pore_pressure is not None:
            flow = self.flow
            for V in (flow.Vp, flow.Vn):
                if not np.array_equal(V.dofmap.list, self.pore_pressure.function_space.dofmap.list):
                    raise RuntimeError("the continuum's pore pressure space does not number the fluid's dofs alike")
            # the continuum's source: its displacement's change over its last step (the
            # volume its pressure increment answered), not the alpha-method's velocity
            self._continuum_rate = fem.Function(self.problem.V)
            flow._fe_u_velocity = self._continuum_rate.sub(0)
            self._w_step.x.array[:] = self.problem.w.x.array
        self.fluid_time = 0.0
        self._interval_force = None   # (free rows, force) of the hook's last interval step
        #: DEM steps per application of the interval's forces (:meth:`_stride`; None: not yet chosen)
        self.stride = None
        if checkpoint is None:
            self._saturate()
        else:
            self._restore_fluid(Path(checkpoint))
        if self.pore_pressure is not None:   # the continuum's n beta_f (n0: the settled grains')
            self.problem.model.storage.value = self.flow.n0 * fluid.compressibility
        what = "saturated" if checkpoint is None else "fluid restored"
        self.log(f"{what} in {time.perf_counter() - t0:.1f} s: k = {fluid.permeability:.3g} m^2, "
                 f"c_v = {self.consolidation_coefficient():.3g} m^2/s, V = v d / c_v = "
                 f"{self.normalised_velocity():.3g}, window porosity {self.flow.n0:.3f}")

    def _continuum_model(self):
        """Continuum = "biot": the dry run's model in total stress, with the pore pressure's
        increment over an FE step as a field (`granfe.models.undrained_split.UndrainedSplit`:
        the FE step holds the fluid's mass, the fluid steps after it drain it)."""
        model = super()._continuum_model()
        if self.fluid.continuum != "biot":
            return model
        if not model.linear:
            raise ValueError(f"fluid.continuum = 'biot' takes an elastic continuum so far, got "
                             f"continuum.model = {self.prm.continuum!r} (or fluid.continuum = 'drained')")
        if self.prm.dim != 2:
            raise ValueError(BIOT_3D)
        return UndrainedSplit(model, storage=0.5 * self.fluid.compressibility,   # (n0's, once measured)
                              mobility=self.fluid.permeability / self.fluid.viscosity)

    def _continuum_loads(self) -> None:
        """Continuum = "biot": the loads of its FE step (`UndrainedSplit`): the fluid's last
        pressure p_f on the skeleton's share, ``int s p_f div(du) dx``, the fluid's mass from
        the step's start, ``-int s div(u_n) dp dx``, and p_f's own flow over the step to the
        alpha-method's forces, ``int tau kappa grad(p_f) . grad(dp) dx``; the increment is 0
        where the fluid drains (the surface)."""
        if self.fluid.continuum != "biot":
            return
        problem = self.problem
        if self.prm.continuum_integrator == "explicit":
            raise ValueError("fluid.continuum = 'biot' needs the implicit continuum "
                             "(continuum.integrator = 'implicit')")
        V = fem.functionspace(problem.domain, ("Lagrange", 1))
        self.pore_pressure = fem.Function(V, name="pore_pressure")   # p_f (the last fluid step's)
        self._w_step = fem.Function(problem.V)                       # the FE step's start
        model = problem.model
        s, p_f, u_n = model.share, self.pore_pressure, problem.split(self._w_step)[0]
        problem.volume_work(lambda dw: s * p_f * ufl.div(dw[0]) - s * ufl.div(u_n) * dw[-1]
                            + model.step * model.mobility * ufl.inner(ufl.grad(p_f), ufl.grad(dw[-1])))
        # (the alpha-method's forces are (1 - alpha_f) dt into the step: the flow's time there)
        model.step.value = (1.0 - AlphaParameters(RHO_INF).alpha_f) * self.dt_fe
        problem.fix("top", "p")

    def _pressure_to_continuum(self) -> None:
        if self.pore_pressure is not None:
            self.pore_pressure.x.array[:] = self.flow.p.x.array

    def _continuum_stepped(self) -> None:
        """After an FE step (before the next sub-cycle's fluid steps): the continuum's
        displacement rate over it (the fluid's source over the sub-cycle), and the next FE
        step's start."""
        if self.pore_pressure is None:
            return
        # (the stepper's predictor is in w already: the last step's end is its w_old)
        w, w_step = self.stepper.w_old.x.array, self._w_step.x.array
        self._continuum_rate.x.array[:] = (w - w_step) / self.dt_fe
        w_step[:] = w

    def consolidation_coefficient(self) -> float:
        """c_v = k M / mu_f [m^2/s], M the continuum's constrained modulus (the packing's)."""
        return self.fluid.consolidation_coefficient(self.flow.M)

    def normalised_velocity(self) -> float:
        """V = v d / c_v (d the cone's diameter): drained below ~0.3, undrained above ~30
        (Randolph & Hope 2004; DeJong & Randolph 2012)."""
        return self.prm.velocity * 2 * self.prm.cone_radius / self.consolidation_coefficient()

    def saturation_permeability(self) -> float:
        """The permeability [m^2] the window saturates with: the run's, or higher, so that
        the window's depth consolidates in a tenth of ``saturation_time`` (c_v t = 10 L^2):
        the rebound from the buoyancy and the packing's own creep drain before the push, as
        a deposit's have long before a sounding."""
        t, L = max(self.fluid.saturation_time, 1e-30), self.prm.window_depth
        drained = 10 * self.fluid.viscosity * L**2 / (self.flow.M * t)
        return max(self.fluid.permeability, drained)

    def _saturate(self) -> None:
        """The window under buoyancy and a drained fluid for ``saturation_time``, the ghosts
        and the penetrator held; the grains' reference positions are taken again."""
        sim, m = self.sim, self.prm.substeps   # (drained: the fluid step of an FE step)
        steps = int(np.ceil(self.fluid.saturation_time / sim.dt / m))
        self.flow.cone_speed = 0.0
        self.flow.set_permeability(self.saturation_permeability())
        for _ in range(steps):
            self.flow.step(m * sim.dt)
            sim.step(m, drag=self.flow.drag)
        self.flow.cone_speed = self.prm.velocity
        self.flow.set_permeability(self.fluid.permeability)
        self.x_ref[:] = sim.p.x[:self.n_grains]
        # the exchange's basis at the new reference, built as a restart builds it (its rows
        # were the settled grains': the projection would read the saturated window at stale
        # positions)
        self.problem.bcs[:] = [bc for bc in self.problem.bcs if bc is not self.interface.bc]
        self.interface = self._displacement_interface()
        self.accelerator = self._accelerator()
        self.flow.p.x.array[:] = 0.0   # the push starts from hydrostatic

    # ---- checkpoints ----------------------------------------------------------------------
    def _checkpoint_files(self, tmp: Path) -> list[str]:
        """The fluid's part of a checkpoint (every rank: its pressure dofs and located points;
        the rest is the same on every rank): :meth:`ChamberFlow.state_dict`, the fluid's
        run time, and the last DEM step's interval force, which the grains' forces in the
        checkpoint hold and the next fluid step takes out (:meth:`_withdraw`)."""
        comm = self.comm
        name = f"fluid_rank{comm.rank}_of{comm.size}.npz"
        last = {}
        if self.pore_pressure is not None:   # (the continuum's state its next rate is from)
            last = {"continuum_w_step": self._w_step.x.array}
        if self.stride is not None:
            last["stride"] = self.stride
        np.savez(tmp / name, **self.flow.state_dict(), fluid_time=self.fluid_time,
                 withdraw=self._pending_interval_force(), **last)
        return [name]

    def _pending_interval_force(self) -> np.ndarray:
        """(n, 3) [N] the interval force in the grains' force rows now (:meth:`_withdraw`'s)."""
        out = np.zeros((self.sim.p.n, 3))
        response = self.flow.response
        if response is not None:
            free = self.sim.p.kind[response.rows] == FREE
            out[response.rows[free]] = response.force[free]
        if self._interval_force is not None:
            free, f = self._interval_force
            out[free] = f[free]
        return out

    @staticmethod
    def _fluid_file(directory: Path, comm) -> Path:
        """This rank's fluid file of the checkpoint in ``directory`` (FileNotFoundError
        naming a dry run's)."""
        path = directory / f"fluid_rank{comm.rank}_of{comm.size}.npz"
        if not path.is_file():
            raise FileNotFoundError(f"the checkpoint in {directory} has no pore fluid of rank "
                                    f"{comm.rank} (no {path.name}): written by a dry run?")
        return path

    def _restore_fluid(self, directory: Path) -> None:
        """The fluid's state from a checkpoint (the grains, the continuum and the history
        were read by the base class): the push continues as the run it was written by."""
        comm = self.comm
        d = dict(np.load(self._fluid_file(directory, comm)))
        missing = [k for k in ("p", "t", "n0", "packed", "withdraw", "fluid_time") if k not in d]
        if missing:
            raise FileNotFoundError(f"the checkpoint in {directory} is not a saturated "
                                    f"penetration's (no fluid {', '.join(missing)})")
        self.flow.load_state(d)
        self._pressure_to_continuum()
        if self.pore_pressure is not None:
            if "continuum_w_step" not in d:
                raise ValueError(f"the checkpoint in {directory} is of a drained continuum "
                                 "(fluid.continuum = 'drained'); this run's is 'biot'")
            if d["continuum_w_step"].shape != self._w_step.x.array.shape:
                raise ValueError("checkpoint field fluid continuum_w_step does not fit this mesh")
            self._w_step.x.array[:] = d["continuum_w_step"]
        self.fluid_time = float(d["fluid_time"])
        if "stride" in d:     # (the run's choice, not one measured at the restart's state)
            self.stride = int(d["stride"])
        pending = d["withdraw"]
        if pending.shape != (self.sim.p.n, 3):
            raise ValueError(f"checkpoint field fluid withdraw has {pending.shape} rows, the "
                             f"run {self.sim.p.n} particles")
        # the last DEM step's interval force, as the next fluid step would take it out
        rows = np.flatnonzero(pending.any(axis=1))
        self.sim.p.force[rows] -= pending[rows]

    def _fluid_step(self) -> None:
        t0 = time.perf_counter()
        self.flow.step(self.fluid.every * self.sim.dt)
        self._pressure_to_continuum()
        self.fluid_time += time.perf_counter() - t0

    def _before_sub_cycle(self, hook) -> dict:
        """A fluid step now (the grains and the continuum as they are), read at the FE step's
        start, and the sub-cycle's `dem.Simulation.step` arguments, ``hook`` last in every
        DEM step. ``fluid.every`` = 1: a hook solves the fluid again after every DEM step's
        force pass and applies its implicit drag. every > 1: a fluid step in the pause after
        every ``every``-th DEM step (between steps), the DEM steps between taking the
        interval's forces: on one rank without an exchange hook as the DEM's linear
        response (`ChamberFlow.interval_response`, in the fused step loop), else from a
        hook (`ChamberFlow.interval_forces`, collective). The last interval force is taken
        out of the grains' forces before a fluid step (which sets the fluid's own)."""
        self._withdraw()
        self._continuum_stepped()
        self._fluid_step()
        self._readings = self.flow.readings()
        sim, every = self.sim, self.fluid.every
        if every == 1:
            count = 0

            def fluid_hook():
                nonlocal count
                count += 1
                if count < self.prm.substeps:
                    self._fluid_step()
                if self.flow.drag is not None:
                    self.flow.drag.apply(sim)
                return bool(hook()) if hook is not None else False
            return {"hook": fluid_hook}
        if hook is None and self.comm.size == 1:
            response = self._response()

            def pause():
                self._withdraw()
                self._fluid_step()
                self._response()
            return {"hook": None, "response": response, "pause_every": every, "pause": pause}
        since, stride = 0, self._stride()

        def interval_hook():
            nonlocal since
            since += 1
            if applies(since, stride):     # (the stride's blocks, as LinearResponse's)
                self._interval_step(since * sim.dt, stride)
            else:
                self._interval_force = None
            return bool(hook()) if hook is not None else False

        def pause():
            nonlocal since
            since = 0
            self._withdraw()
            self._fluid_step()
        return {"hook": interval_hook, "pause_every": every, "pause": pause}

    def _withdraw(self) -> None:
        """Take the last DEM step's interval force out of the grains' forces (between steps,
        before a fluid step sets the fluid's own: else the next half-kick counts it twice)."""
        if self.flow.response is not None:
            self.flow.response.withdraw(self.sim)
        if self._interval_force is not None:
            free, f = self._interval_force
            self.sim.p.force[free] -= f[free]
            self._interval_force = None

    def _response(self) -> LinearResponse:
        t0 = time.perf_counter()
        response = self.flow.interval_response()
        response.stride = self._stride()
        self.fluid_time += time.perf_counter() - t0
        return response

    #: the largest ``s dt omega`` a response stride s may reach (the impulse method is stable
    #: below 2; at 0.5 the stiffest mode's period is 1.1 % short)
    STRIDE_LIMIT = 0.5

    def _stride(self) -> int:
        """The DEM steps per application of the interval's forces: the largest divisor s of
        ``fluid.every`` up to ``fluid.response_every`` with ``s dt omega`` <= STRIDE_LIMIT,
        omega the interval's stiffest frequency at the push's first fluid step (power
        iteration: once a run, kept by checkpoints). Collective the first time."""
        if self.stride is None:
            every, most = self.fluid.every, self.fluid.response_every
            self.stride = 1
            if most > 1:
                t0 = time.perf_counter()
                omega_dt = self.flow.stiffest() * self.sim.dt
                fits = [s for s in range(1, most + 1) if every % s == 0 and s * omega_dt <= self.STRIDE_LIMIT]
                self.stride = max(fits, default=1)
                self.log(f"fluid: the interval's forces once in {self.stride} DEM steps (response_every "
                         f"{most}; its stiffest mode omega dt = {omega_dt:.3g}, measured in "
                         f"{time.perf_counter() - t0:.2f} s)")
        return self.stride

    def _interval_step(self, elapsed: float, weight: int = 1) -> None:
        """The fluid's force change ``elapsed`` [s] after its last step (times ``weight``: a
        stride's impulse), added to the free grains' forces of this DEM step
        (:meth:`ChamberFlow.interval_forces`)."""
        t0 = time.perf_counter()
        sim = self.sim
        f = self.flow.interval_forces(elapsed)
        if weight != 1:
            f *= weight
        free = sim.p.kind == FREE
        sim.p.force[free] += f[free]
        sim.forced[free] = 1
        self._interval_force = (free, f)
        self.fluid_time += time.perf_counter() - t0

    def advance(self) -> dict:
        record = super().advance()
        record.update(self._readings, q_t=record["q_c"] + self._readings["q_u"])
        return record

    def summary(self) -> dict:
        """The fluid's parameters and the run's drainage figures (for results.json)."""
        return {"permeability": self.fluid.permeability, "viscosity": self.fluid.viscosity,
                "compressibility": self.fluid.compressibility, "density": self.fluid.density,
                "bulk_modulus": self.flow.K, "constrained_modulus": self.flow.M,
                "c_v": self.consolidation_coefficient(), "V": self.normalised_velocity(),
                "porosity_window": self.flow.n0, "fluid_time_s": self.fluid_time}
