"""A compressible Darcy pore fluid through the grains, on a dolfinx mesh covering them.

The fluid model of Damsgaard's ``sphere`` (seed 003, eq. 5.4-5.5, after Goren et al. 2011):
no fluid inertia, Darcy's law for the flux relative to the grains

    n (v_f - v_s) = -(k / mu_f) grad p                                        (seed 003 eq. 5.5)

with ``p`` the deviation from the hydrostatic pressure, and the fluid and (incompressible)
solid mass balances summed into one transient diffusion equation for ``p`` with the grains'
volumetric change as its source:

    n beta_f dp/dt + div v_s - div((k / mu_f) grad p) = 0.

It is solved by backward Euler in P1 (or P2) with the grains as they are when it is solved
(``beta_f = 0``: the steady, incompressible limit). Weak form, test function ``q``, inflow
``g`` [m/s] on flux boundaries (``v_s . n = 0`` on the boundary: the grains stay inside):

    (n beta_f / dt) (p - p_old, q) + ((k / mu_f) grad p - v_s, grad q) = <g, q>.

From the grains, with the FE basis evaluated at their centroids (the N of
`coupling.operators.FieldBasis`, kept here as its rows, one per grain): the
solid fraction is the lumped-mass projection ``phi_a = sum_i V_i N_a(x_i) / int N_a``
(``DG0``, the default: the grains' volumes binned into cells; ``P1``: averaged over each
node's support, twice the volume, so smoother; a linear N weighs a grain's body as its
centroid, so both are exact for a lattice filling the cells, and both conserve sum V_i), the
porosity ``n = 1 - phi`` (clipped to ``[porosity_min, porosity_max]``), and the grains' mean
velocity ``v_s,a = sum_i V_i v_i N_a(x_i) / sum_i V_i N_a(x_i)``. The permeability is
Kozeny-Carman ``k = d^2 n^3 / (C (1 - n)^2)`` or a constant. The averaging volume is the
cell (DG0) or the node's support (P1): it must hold tens of grains, or the scatter of n
makes k (~n^3) and the forces noisy (measured: Kozeny-Carman flux within 1 % with ~40
grains per cell, 27 % off with ~12 per triangle). With P1 a boundary node averages its
half-support only, the grains against the wall or the surface, so its porosity and its
Kozeny-Carman k (~n^3) are the boundary layer's: a consolidating lattice column drained at
the top, 6 cells high, ran ahead of Terzaghi with P1 (T50 0.14 against 0.197; DG0 0.19,
demos/2d/grain_consolidation.py), where at a constant k the two agree.

Back to the grains, through `dem.Simulation.set_external_force` (FREE rows, held over the
DEM steps of one fluid step, their change with the grains' motion in the meantime taken
implicitly: :class:`DarcyFlow`): the fluid's force on the skeleton per bulk volume is
``-grad p`` (drag and the excess-pressure buoyancy of Darcy flow) plus the hydrostatic
buoyancy. It is handed out by the transpose of the averaging that made the solid fraction:
each dof's share ``F_a = -int N_a grad p dx`` goes to the grains in proportion to the
weights ``V_i N_a(x_i)`` they gave its solid fraction,

    f_i = V_i sum_a N_a(x_i) F_a / S_a - rho_f V_i g,   S_a = sum_j V_j N_a(x_j),

so the grains get exactly ``-int grad p dx``, cell by cell (DG0) or dof by dof (P1): the
reaction to the drag the fluid feels (``S_a`` is at least ``(1 - porosity_max) int N_a``,
the clipping of n). For a uniform porosity it is ``-V_i grad p / (1 - n)``. The point value
``-V_i grad p(x_i) / (1 - n(x_i))`` instead is not conservative where n varies within a
dof's support: with P1 on a rough drained surface the top row of grains got ~78 % of the
seepage force it carries, and a column of grains consolidated ahead of Terzaghi's curve
(a hexagonal lattice, elastic: T50 0.135 against 0.197; 0.19 conservative).

2D: disks of unit thickness (volume = area, forces per metre). Parallel: the grains are held
whole on every rank (a replicated `dem.Simulation`); each rank evaluates the grains whose
centroid lies in its cells and the forces are summed over the ranks (each grain on one rank:
the sum is exact, so every rank applies the same bits). Nothing here runs unless a
:class:`DarcyFlow` is created.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)
from mpi4py import MPI
from petsc4py import PETSc

import basix.ufl
import numpy as np
import ufl
from dolfinx import default_scalar_type, fem, la
from dolfinx import mesh as _mesh
from dolfinx.fem.petsc import LinearProblem, assemble_matrix, assemble_vector
from scipy import sparse

from coupling.locate import affine_maps, cell_tree, locate_owned, owner_ranks, relocate
from dem.drag import GroupDrag, group_means
from dem.state import FREE
from granfe.problem import Where, boundary_facets
from granfe.solvers import REDUNDANT, check_ksp_converged

__all__ = ["DarcyFlow", "GrainSpace", "PoreFluidParameters", "kozeny_carman", "grain_volumes"]


@dataclass(frozen=True)
class PoreFluidParameters:
    """The pore fluid and how the grains are seen by it (SI units), validated on construction.

    Attributes:
        viscosity: dynamic viscosity mu_f [Pa s], > 0 (water: 1e-3).
        compressibility: adiabatic compressibility beta_f [1/Pa], >= 0 (water: 4.5e-10);
            0 is the steady (incompressible) limit, which needs a pressure boundary.
        density: rho_f [kg/m^3], >= 0: the hydrostatic buoyancy ``-rho_f V g``.
        permeability: a constant k [m^2] > 0, or None for Kozeny-Carman.
        kozeny_carman: the Kozeny-Carman constant C > 0 (180 for spheres).
        grain_diameter: d [m] > 0 in Kozeny-Carman; None: the grains' Sauter mean
            ``2 dim sum V / sum S`` (= 2 r for equal grains).
        porosity_min, porosity_max: the porosity is clipped to this range (empty cells,
            crammed cells), 0 < min < max < 1.
        porosity_space: ``"DG0"`` (cell binning) or ``"P1"`` (nodal, smoother, but its
            boundary nodes see the boundary layer's porosity: the module docstring) for n
            and v_s.
        pressure_degree: Lagrange degree of p, 1 or 2.
        implicit_drag: the velocity components (``"all"``, ``"none"`` or axes such as
            ``"y"``, ``"xz"``) whose cell-mean changes between two fluid steps feel the
            fluid's linearised response at once (:attr:`DarcyFlow.drag`); leave out
            the axes along which the fluid cannot resist a uniform motion (a periodic
            direction), where the drag would only slow the cell-mean's changes.
    """

    viscosity: float = 1.0e-3
    compressibility: float = 4.5e-10
    density: float = 1000.0
    permeability: float | None = None
    kozeny_carman: float = 180.0
    grain_diameter: float | None = None
    porosity_min: float = 0.05
    porosity_max: float = 0.95
    porosity_space: str = "DG0"
    pressure_degree: int = 1
    implicit_drag: str = "all"

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("permeability", "grain_diameter") and v is None:
                continue
            if f.name == "implicit_drag":
                if not (v in ("all", "none") or (isinstance(v, str) and v
                                                 and set(v) <= set("xyz")
                                                 and len(set(v)) == len(v))):
                    raise ValueError(f"PoreFluidParameters.implicit_drag must be 'all', "
                                     f"'none' or axes such as 'y' or 'xz', got {v!r}")
                continue
            if f.name == "porosity_space":
                if v not in ("DG0", "P1"):
                    raise ValueError(f"PoreFluidParameters.porosity_space must be 'DG0' or "
                                     f"'P1', got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"PoreFluidParameters.{f.name} must be a finite number, "
                                 f"got {v!r}")
        positive = ("viscosity", "kozeny_carman", "permeability", "grain_diameter")
        for name in positive:
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"PoreFluidParameters.{name} must be > 0, got {v!r}")
        for name in ("compressibility", "density"):
            if getattr(self, name) < 0:
                raise ValueError(f"PoreFluidParameters.{name} must be >= 0, got "
                                 f"{getattr(self, name)!r}")
        if not 0 < self.porosity_min < self.porosity_max < 1:
            raise ValueError(f"PoreFluidParameters.porosity_min/porosity_max must satisfy "
                             f"0 < min < max < 1, got {self.porosity_min!r}, "
                             f"{self.porosity_max!r}")
        if self.pressure_degree not in (1, 2):
            raise ValueError(f"PoreFluidParameters.pressure_degree must be 1 or 2, got "
                             f"{self.pressure_degree!r}")


def kozeny_carman(n, d: float, C: float = 180.0):
    """Kozeny-Carman permeability ``k = d^2 n^3 / (C (1 - n)^2)`` [m^2] of porosity n (numbers,
    arrays or UFL), grain diameter d [m] and constant C."""
    return d**2 * n**3 / (C * (1 - n) ** 2)


def grain_volumes(radius: np.ndarray, dim: int) -> np.ndarray:
    """Volumes [m^3] of spheres (dim 3) or areas [m^2] of disks of unit thickness (dim 2)."""
    r = np.asarray(radius, dtype=float)
    return math.pi * r**2 if dim == 2 else 4.0 / 3.0 * math.pi * r**3


class DarcyFlow:
    """The pore pressure of a Darcy fluid through the grains of a DEM run, and its forces.

    Args:
        domain: a dolfinx mesh (triangles/tetrahedra or quads/hexes) covering every grain.
        sim: the `dem.Simulation` (held whole on every rank); its ``gravity`` sets buoyancy.
        params: :class:`PoreFluidParameters`.
        facet_tags, tag_names: named boundaries (physical-group names -> tag values).
        petsc_options: overrides of the direct linear solve (LU: PETSc's on one rank,
            sequential MUMPS on every rank of several, `granfe.solvers.REDUNDANT`).
        particles: the fluid sees the first ``particles`` rows of the DEM (None: all): the
            grains, when rigid bodies follow them (a penetrator's clump, which may stand
            outside the mesh); the rows after them have no volume to it and get no force.

    Boundaries are undrained (no flux) unless :meth:`pressure`, :meth:`drained` or
    :meth:`flux` say otherwise. :meth:`step` solves one fluid step and applies the forces;
    :meth:`advance` alternates fluid steps and DEM steps.

    Sub-cycling: the forces of a fluid step are held over its DEM steps, and their change
    with the grains' cell-mean velocity U since the fluid step is taken implicitly in every
    DEM step (:attr:`drag`, `dem.drag.GroupDrag`): the fluid's response to U is, per
    grain, the drag ``-alpha_i (U - U_ref)`` with

        alpha_i = V_i mu_f / (k (1 - n)) * D / (1 + D),   D = k dt_f pi^2 / (mu_f n beta_f h^2),

    the Darcy drag of a compaction wave of the cell's size h (1D: ``k/mu grad p = v_s``), cut
    by the storage where the fluid step dt_f is too short for the pressure to diffuse over a
    cell (D < 1: undrained, the fluid a spring of stiffness ~ pi^2 / (n beta h^2) dt_f). Held
    explicitly instead, that drag is unstable once dt_f exceeds twice the relaxation time
    ``rho_s (1 - n) k / mu_f`` (measured on the consolidation column: blow-up between 8 and
    12 DEM steps per fluid step with 2 tau = 15 DEM steps, halving with tau; the same with
    beta_f = 0, so the drag, not the compressibility). The linearised drag bounds the true
    response (a Darcy drag on the irrotational part of v_s at most), so the sub-cycled
    iteration is stable for any dt_f and its fixed point is the fluid's.
    """

    def __init__(self, domain: _mesh.Mesh, sim, params: PoreFluidParameters | None = None, *,
                 facet_tags: _mesh.MeshTags | None = None, tag_names: dict | None = None,
                 petsc_options: dict | None = None, particles: int | None = None):
        self.params = params = params or PoreFluidParameters()
        if not isinstance(params, PoreFluidParameters):
            raise TypeError(f"params must be PoreFluidParameters, got {type(params).__name__}")
        self.domain, self.sim = domain, sim
        gdim = domain.geometry.dim
        if sim.p.dim != gdim:
            raise ValueError(f"a {gdim}D mesh for {sim.p.dim}D grains")
        self.facet_tags, self.tag_names = facet_tags, dict(tag_names or {})
        self.volume = grain_volumes(sim.p.radius, sim.p.dim)
        self.particles = sim.p.n if particles is None else int(particles)
        if not 0 < self.particles <= sim.p.n:
            raise ValueError(f"particles must lie in [1, {sim.p.n}] (the DEM's rows), got "
                             f"{particles!r}")
        self.volume[self.particles:] = 0.0
        self.d = params.grain_diameter or self._sauter_diameter()
        cell = domain.basix_cell()
        fam, deg = ("DG", 0) if params.porosity_space == "DG0" else ("Lagrange", 1)
        pdeg = params.pressure_degree
        # one basis at the grains for the scalar and the vector fields (the vector space is
        # the scalar one blocked: component c of dof a is local entry a * gdim + c)
        self._grains = GrainSpace(domain, basix.ufl.element(fam, cell, deg))
        self.Vn = self._grains.V
        self.Vv = fem.functionspace(domain, basix.ufl.element(fam, cell, deg, shape=(gdim,)))
        if not np.array_equal(self.Vv.dofmap.list, self.Vn.dofmap.list):
            raise RuntimeError("the vector grain space does not block the scalar one")
        self.Vp = fem.functionspace(domain, basix.ufl.element("Lagrange", cell, pdeg))
        self.porosity = fem.Function(self.Vn, name="porosity")
        self.velocity = fem.Function(self.Vv, name="grain_velocity")
        self.p = fem.Function(self.Vp, name="pore_pressure")
        self.p_old = fem.Function(self.Vp)
        #: F_a = -int N_a grad p dx on Vv: the fluid's force on the skeleton, dof by dof
        self.nodal_force = fem.Function(self.Vv, name="seepage_force")
        # p -> F: the mesh's, assembled once
        self._force_matrix = assemble_matrix(fem.form(-ufl.inner(
            ufl.grad(ufl.TrialFunction(self.Vp)), ufl.TestFunction(self.Vv)) * ufl.dx))
        self._force_matrix.assemble()
        self.lumped_mass = self._lumped_mass(self.Vn)  #: int N_a dx of the local dofs of Vn
        self._storage = fem.Constant(domain, default_scalar_type(0.0))  # beta_f / dt
        self._inv_dt = fem.Constant(domain, default_scalar_type(0.0))   # 1 / dt (0: steady)
        #: a storage [1/Pa] beside the fluid's ``n beta_f`` (a UFL expression on the mesh, set
        #: before the first solve), e.g. the compressibility of a skeleton whose volume change
        #: is not the grains' (:mod:`coupling.apps.penetration.saturated`); None: none
        self.skeleton_storage = None
        self.bcs: list = []
        self._neumann: list = []
        self._problem = None
        # LU: PETSc's own on one rank (MUMPS's set-up per factorisation is most of a small
        # mesh's solve); across ranks sequential MUMPS on every rank (granfe.solvers.REDUNDANT:
        # parallel MUMPS schedules dynamically, and its round-off, grown by the grains, made
        # two runs on the same ranks, or a restart, part)
        serial = {"pc_type": "lu", "pc_factor_mat_solver_type": "petsc"}
        self._petsc = {"ksp_type": "preonly", **(serial if domain.comm.size == 1 else REDUNDANT),
                       **(petsc_options or {})}
        self._mine = None   # global rows of the grains this rank evaluates
        # the mesh does not move: its pull-backs and its cells' search tree once
        self._maps, self._tree = affine_maps(domain), cell_tree(domain)
        self.forces = np.zeros((sim.p.n, 3))  #: the fluid's force on every grain [N] (last step)
        #: other forces [N] (n, 3) handed to the DEM with the fluid's (e.g. a surcharge):
        #: `dem.Simulation.set_external_force` holds one set, which :meth:`apply_forces` sets
        self.extra_force: np.ndarray | None = None
        self.t = 0.0
        self.drag: GroupDrag | None = None  #: the implicit drag of the last fluid step
        self._scratch: dict = {}
        self._dt = None       # the last fluid step [s] (None: steady)
        g = domain.geometry
        xc = g.x[g.dofmaps[0]][:, :, :gdim]
        self._cell_size = (xc.max(axis=1) - xc.min(axis=1)).min(axis=1)  # local cells [m]
        self.grains_to_mesh()
        self.porosity.x.array[:] = 1.0 - self._solid_fraction()
        self._clip_porosity()

    # ---- grains -> mesh ----------------------------------------------------------------
    def _sauter_diameter(self) -> float:
        r, dim = self.sim.p.radius[:self.particles], self.sim.p.dim
        surface = 2 * math.pi * r if dim == 2 else 4 * math.pi * r**2
        return float(2 * dim * self.volume.sum() / surface.sum())

    def _lumped_mass(self, V) -> np.ndarray:
        """The integrals int N_a dx of every local dof of the scalar space V (owned, ghost)."""
        m = fem.Function(V)
        vec = assemble_vector(fem.form(ufl.TestFunction(V) * ufl.dx))
        vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        m.x.petsc_vec.array_w[:] = vec.array_r
        vec.destroy()
        m.x.scatter_forward()
        return m.x.array.copy()

    def grains_to_mesh(self) -> None:
        """Locate the grains again and evaluate the basis at their centroids (collective).
        While every grain stays in its rank's cells only the moved ones are searched for; if
        one left them (another rank's cells, or the mesh) the grains are shared out anew
        (:func:`coupling.locate.owner_ranks` names those outside)."""
        x = self.positions()
        if self._mine is not None:
            mine = self._mine
            cells, X, _, lost = relocate(self.domain, x[mine], self._grains.cells,
                                         maps=self._maps, tree=self._tree)
            if self.domain.comm.allreduce(int(lost.sum())) == 0:
                self._grains.evaluate(cells, X)
                return
        owners = owner_ranks(self.domain, x)
        self._mine = np.flatnonzero(owners == self.domain.comm.rank)
        self._grains.evaluate(*locate_owned(self.domain, x[self._mine], tree=self._tree))

    def positions(self) -> np.ndarray:
        """(particles, gdim) [m] the grains' centroids where the fluid bins them: where they
        are (a subclass may bring those that left the mesh back to its edge, e.g. grains
        heaved above a free surface that the mesh ends at)."""
        return self.sim.p.x[:self.particles, : self.domain.geometry.dim]

    def _work(self, name: str, V) -> fem.Function:
        """A scratch Function on V kept between fluid steps (its PETSc wrapper is made once)."""
        f = self._scratch.get(name)
        if f is None:
            f = self._scratch[name] = fem.Function(V)
        return f

    def _solid_fraction(self) -> np.ndarray:
        """Lumped-mass projection sum_i V_i N_a(x_i) / int N_a of the local dofs of Vn."""
        f = self._work("solid", self.Vn)
        self._grains.sum_to(self.volume[self._mine], f)
        return f.x.array / self.lumped_mass

    def _clip_porosity(self) -> None:
        a = self.porosity.x.array
        np.clip(a, self.params.porosity_min, self.params.porosity_max, out=a)

    def _mean_velocity(self) -> None:
        """v_s = sum V_i v_i N_a / sum V_i N_a (0 where no grain is near)."""
        gdim = self.domain.geometry.dim
        p, mine = self.sim.p, self._mine
        self._grains.sum_to(self.volume[mine, None] * p.v[mine, :gdim], self.velocity)
        v = self.velocity.x.array.reshape(-1, gdim)
        d = self._work("solid", self.Vn).x.array   # sum_i V_i N_a(x_i), of this update
        np.divide(v, d[:, None], out=v, where=d[:, None] > 0)

    def update_from_grains(self) -> None:
        """Porosity and mean grain velocity on the mesh from the grains now (collective). The
        grains keep their number and radii (volumes are taken once)."""
        self.grains_to_mesh()
        self.porosity.x.array[:] = 1.0 - self._solid_fraction()
        self._clip_porosity()
        self._mean_velocity()     # after the solid fraction: it divides by its sums

    def solid_volume(self) -> float:
        """The grains' volume sum V_i [m^3] (= int (1 - n) dx before clipping)."""
        return self.domain.comm.allreduce(float(self.volume[self._mine].sum()))

    # ---- boundaries ----------------------------------------------------------------------
    def facets(self, where: Where) -> np.ndarray:
        """Local boundary facets of a named group, a tag value, or a locator ``x -> bool``."""
        return boundary_facets(self.domain, self.facet_tags, self.tag_names, where)

    def pressure(self, where: Where, value: float = 0.0) -> fem.Constant:
        """Prescribed pore pressure (deviation from hydrostatic) [Pa] on a boundary; returns
        the constant holding it (set ``.value`` between steps)."""
        holder = fem.Constant(self.domain, default_scalar_type(_finite("pressure", value)))
        fdim = self.domain.topology.dim - 1
        dofs = fem.locate_dofs_topological(self.Vp, fdim, self.facets(where))
        self.bcs.append(fem.dirichletbc(holder, dofs, self.Vp))
        self._problem = None
        return holder

    def drained(self, where: Where) -> fem.Constant:
        """A drained boundary: p = 0 (hydrostatic)."""
        return self.pressure(where, 0.0)

    def flux(self, where: Where, value: float = 0.0) -> fem.Constant:
        """Prescribed fluid inflow [m/s] (volume per area and time, into the domain) on a
        boundary; returns the constant holding it."""
        holder = fem.Constant(self.domain, default_scalar_type(_finite("flux", value)))
        facets = self.facets(where)
        tag = len(self._neumann) + 1
        self._neumann.append((facets, tag, holder))
        self._problem = None
        return holder

    # ---- solve ---------------------------------------------------------------------------
    def permeability(self):
        """The permeability k [m^2]: a UFL expression of the porosity, or the constant."""
        prm = self.params
        if prm.permeability is not None:
            return fem.Constant(self.domain, default_scalar_type(prm.permeability))
        return kozeny_carman(self.porosity, self.d, prm.kozeny_carman)

    def _forms(self):
        p, q = ufl.TrialFunction(self.Vp), ufl.TestFunction(self.Vp)
        k_mu = self.permeability() / self.params.viscosity
        n, s = self.porosity, self._storage
        a = s * n * p * q * ufl.dx + k_mu * ufl.inner(ufl.grad(p), ufl.grad(q)) * ufl.dx
        L = s * n * self.p_old * q * ufl.dx + ufl.inner(self.velocity, ufl.grad(q)) * ufl.dx
        if self.skeleton_storage is not None:
            c = self._inv_dt * self.skeleton_storage
            a += c * p * q * ufl.dx
            L += c * self.p_old * q * ufl.dx
        ds = self._ds()
        for _, tag, g in self._neumann:
            L += g * q * ds(tag)
        return a, L

    def _ds(self):
        if not self._neumann:
            return ufl.ds
        fdim = self.domain.topology.dim - 1
        ent = np.concatenate([f for f, _, _ in self._neumann]).astype(np.int32)
        val = np.concatenate([np.full(len(f), t, np.int32) for f, t, _ in self._neumann])
        order = np.argsort(ent, kind="stable")
        tags = _mesh.meshtags(self.domain, fdim, ent[order], val[order])
        return ufl.Measure("ds", domain=self.domain, subdomain_data=tags)

    def _residual_form(self):
        """The mass balance tested with q: at a boundary's dofs, the inflow there."""
        q = ufl.TestFunction(self.Vp)
        k_mu = self.permeability() / self.params.viscosity
        r = (self._storage * self.porosity * (self.p - self.p_old) * q
             + ufl.inner(k_mu * ufl.grad(self.p) - self.velocity, ufl.grad(q))) * ufl.dx
        if self.skeleton_storage is not None:
            r += self._inv_dt * self.skeleton_storage * (self.p - self.p_old) * q * ufl.dx
        ds = self._ds()
        for _, tag, g in self._neumann:
            r -= g * q * ds(tag)
        return fem.form(r)

    def solve(self, dt: float | None = None) -> fem.Function:
        """The pressure after a backward-Euler step of ``dt`` [s] from the last one, with the
        grains as they are now (``dt=None`` or ``compressibility = 0``: steady). Does not
        touch the grains' forces. Collective."""
        if dt is not None and not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (fluid time step) must be > 0 s, got {dt!r}")
        steady = dt is None or self.params.compressibility == 0
        if steady and not self.domain.comm.allreduce(int(any(len(bc.dof_indices()[0])
                                                             for bc in self.bcs)), op=MPI.MAX):
            raise ValueError("a steady (incompressible) pore fluid needs a pressure boundary "
                             "(drained or prescribed): with flux boundaries only p is not "
                             "determined")
        self.update_from_grains()
        self.p_old.x.array[:] = self.p.x.array
        self._storage.value = 0.0 if steady else self.params.compressibility / dt
        self._inv_dt.value = 0.0 if dt is None else 1.0 / dt
        if self._problem is None:
            a, L = self._forms()
            self._problem = LinearProblem(a, L, bcs=self.bcs, u=self.p,
                                          petsc_options_prefix=f"granfe_darcy_{id(self)}_",
                                          petsc_options=self._petsc)
            self._residual = self._residual_form()
        self._linear_solve()
        self.p.x.scatter_forward()
        if dt is not None:
            self.t += dt
        self._dt = None if steady else dt
        return self.p

    def _linear_solve(self) -> None:
        """The step's system assembled and solved into :attr:`p` (its owned dofs)."""
        self._problem.solve()
        check_ksp_converged(self._problem.solver, "pore fluid")

    def inflow(self, where: Where) -> float:
        """Fluid volume rate entering through a boundary in the last solve [m^3/s; m^2/s in
        2D]: the mass balance's residual at the boundary's pressure dofs (conservative: the
        inflows of all boundaries sum to the storage change and the grains' source)."""
        vec = assemble_vector(self._residual)
        vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        fdim = self.domain.topology.dim - 1
        dofs = fem.locate_dofs_topological(self.Vp, fdim, self.facets(where))
        owned = dofs[dofs < self.Vp.dofmap.index_map.size_local]
        total = float(vec.array_r[owned].sum())
        vec.destroy()
        return self.domain.comm.allreduce(total)

    # ---- mesh -> grains -------------------------------------------------------------------
    def grain_forces(self) -> np.ndarray:
        """The fluid's force on every grain (n, 3) [N] from the last solve: its share of
        ``-int grad p dx`` (the module docstring) plus buoyancy ``-rho_f V g`` (the same on
        every rank)."""
        return self._at_grains()[0]

    def _seepage_per_volume(self) -> fem.Function:
        """F_a / S_a on Vv (the force per grain volume of the grains' share of dof a, from
        the last solve and the solid sums of the last :meth:`update_from_grains`)."""
        gdim = self.domain.geometry.dim
        F = self.nodal_force
        self._force_matrix.mult(self.p.x.petsc_vec, F.x.petsc_vec)
        F.x.scatter_forward()
        floor = (1.0 - self.params.porosity_max) * self.lumped_mass
        share = np.maximum(self._work("solid", self.Vn).x.array, floor)
        g = self._work("seepage", self.Vv)
        g.x.array[:] = (F.x.array.reshape(-1, gdim) / share[:, None]).ravel()
        return g

    def _at_grains(self):
        """(forces (n, 3) [N], drag coefficients alpha (n,) [N s/m], global cell (n,)) of
        every grain, the same on every rank."""
        gdim = self.domain.geometry.dim
        mine = self._mine
        per_volume = self._grains.at_grains(self._seepage_per_volume())
        n = self._grains.at_grains(self.porosity)[:, 0]
        cells = self._grains.cells
        tdim = self.domain.topology.dim
        out = np.zeros((self.sim.p.n, 5))
        out[mine, :gdim] = self.volume[mine, None] * per_volume
        out[mine, 3] = self._drag_coefficient(self.volume[mine], n, self._cell_size[cells])
        out[mine, 4] = self.domain.topology.index_map(tdim).local_to_global(cells) + 1
        comm = self.domain.comm
        if comm.size > 1:     # each grain on one rank: an exact sum
            comm.Allreduce(MPI.IN_PLACE, out, op=MPI.SUM)
        f = np.zeros((self.sim.p.n, 3))
        f[:, :gdim] = out[:, :gdim]
        f -= self.params.density * self.volume[:, None] * self.sim.gravity[None, :]
        return f, out[:, 3], out[:, 4].astype(np.int64) - 1

    def _drag_coefficient(self, V, n, h):
        """The drag coefficients alpha = V mu / (k (1 - n)) D / (1 + D) [N s/m] of grains of
        volume V, porosity n in cells of size h (see the class docstring)."""
        prm = self.params
        k = prm.permeability if prm.permeability is not None else \
            kozeny_carman(n, self.d, prm.kozeny_carman)
        alpha = V * prm.viscosity / (k * (1.0 - n))
        if self._dt is not None and prm.compressibility > 0:
            D = k * self._dt * math.pi**2 / (prm.viscosity * n * prm.compressibility * h**2)
            alpha *= D / (1.0 + D)
        return alpha

    def apply_forces(self) -> None:
        """Hand the fluid's forces (plus :attr:`extra_force`) to the DEM, constant until the
        next call, and set up the implicit drag of the DEM steps until then (:attr:`drag`)."""
        self.forces, alpha, cell = self._at_grains()
        total = self.forces if self.extra_force is None else self.forces + self.extra_force
        free = np.flatnonzero(self.sim.p.kind == FREE)
        self.sim.set_external_force(free, total[free])
        axes = self.params.implicit_drag
        flags = [0.0, 0.0, 0.0] if axes == "none" else \
            [float(axes == "all" or c in axes) for c in "xyz"]
        if not any(flags):
            self.drag = None
            return
        # the cells holding grains, numbered 0..G-1 (a count over the mesh's cells: np.unique
        # sorts, the fluid's step is paid every few DEM steps)
        seen = cell >= 0      # (the rows the fluid does not see have no cell)
        held = np.bincount(cell[seen], minlength=self.domain.topology.index_map(
            self.domain.topology.dim).size_global) > 0
        group = np.where(seen, (np.cumsum(held) - 1)[np.maximum(cell, 0)], -1)
        u_ref = group_means(self.sim.p.v, group, self.volume, int(held.sum()))
        self.drag = GroupDrag(group, self.volume, alpha, u_ref, flags)

    def substep_hook(self):
        """A `dem.Simulation.step` hook for the DEM steps until the next fluid step: the
        implicit drag (None if ``implicit_drag == "none"``). The grains it drags carry the
        fluid's external force, so the DEM's kicks read their force rows."""
        return None if self.drag is None else self.drag.hook(self.sim)

    def step(self, dt: float | None) -> fem.Function:
        """One fluid step of ``dt`` [s] (None: steady) at the grains' state now, then its
        forces to the grains; pass :attr:`drag` to the DEM steps that follow
        (``sim.step(m, drag=flow.drag)``, as :meth:`advance` does; or the slower
        :meth:`substep_hook`, the same bits). Collective."""
        self.solve(dt)
        self.apply_forces()
        return self.p

    def advance(self, dem_steps: int, every: int) -> None:
        """``dem_steps`` DEM steps, a fluid step of ``every`` DEM steps before each block,
        the implicit drag in every DEM step."""
        if not (int(every) >= 1 and int(dem_steps) >= 0):
            raise ValueError(f"every must be >= 1 and dem_steps >= 0, got {every!r}, "
                             f"{dem_steps!r}")
        done = 0
        while done < dem_steps:
            m = min(int(every), dem_steps - done)
            self.step(m * self.sim.dt)
            self.sim.step(m, drag=self.drag)     # (the hook's bits, in the fused loop)
            done += m


class GrainSpace:
    """A scalar DG0/P1 space whose basis N is evaluated at the grains' centroids, acting on
    it and on its blocked vector space (N applied per component). N is kept as its rows:
    the (m, nd) dofs of each grain's cell and the basis values there (the products are a
    gather and a count; no sparse matrix is built each fluid step)."""

    def __init__(self, domain, element):
        self.V = fem.functionspace(domain, element)
        self._element = self.V.ufl_element().basix_element
        self.cells = np.zeros(0, np.int32)     # the grains' owned local cells
        self._cols = self._w = None

    def evaluate(self, cells: np.ndarray, X: np.ndarray) -> None:
        """The basis at the grains in ``cells`` at reference points X (m, tdim)."""
        self.cells = np.asarray(cells, np.int32)
        self._cols = self.V.dofmap.list[self.cells]
        self._w = self._element.tabulate(0, X)[0, :, :, 0] if len(self.cells) else \
            np.zeros(self._cols.shape)

    def sum_to(self, values: np.ndarray, out: fem.Function) -> None:
        """``out = N^T values``: per dof (and component), the sum over the grains of all ranks
        of their values (m,) or (m, bs) times the basis function at their centroid; ``out``
        on V or its blocked space. Collective (the ghosts' sums go to their owners)."""
        bs = out.function_space.dofmap.bs
        a = out.x.array.reshape(-1, bs)
        v = np.asarray(values, dtype=float).reshape(len(self._cols), bs)
        cols = self._cols.ravel()
        for c in range(bs):
            a[:, c] = np.bincount(cols, (self._w * v[:, c, None]).ravel(), minlength=len(a))
        out.x.scatter_reverse(la.InsertMode.add)
        out.x.scatter_forward()

    def rows(self):
        """(dofs (m, nd), basis values (m, nd)) of this rank's grains: N's entries by grain."""
        return self._cols, self._w

    def matrix(self):
        """N as a sparse (local dofs, this rank's grains) matrix (scipy CSR), for callers
        that apply it many times between two evaluations (no ghost sums: one rank's)."""
        m, nd = self._cols.shape
        n = self.V.dofmap.index_map.size_local + self.V.dofmap.index_map.num_ghosts
        return sparse.csr_matrix((self._w.ravel(), (self._cols.ravel(), np.repeat(np.arange(m), nd))),
                                 shape=(n, m))

    def at_grains(self, u: fem.Function) -> np.ndarray:
        """Values (m, bs) of ``u`` (on V or its blocked space) at this rank's grains."""
        a = u.x.array.reshape(-1, u.function_space.dofmap.bs)
        out = self._w[:, :1] * a[self._cols[:, 0]]
        for k in range(1, self._cols.shape[1]):     # (a sum over the cell's dofs)
            out += self._w[:, k:k + 1] * a[self._cols[:, k]]
        return out


def _finite(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} value must be a finite number, got {value!r}")
    return float(value)
