"""The DE window follows the penetrator (seed 000 Fig. 3): when the tip comes within a given
distance of the window's bottom, the window moves down, continuum ahead of the tip becomes
grains and grains far behind become continuum again.

One move (:meth:`MovingWindowPenetration.move`), all in the FE's reference configuration
(small strain: the FE basis is evaluated at reference positions ``X``, a grain sits at
``x = X + u(X)``):

1. the window Box's bottom goes down by ``step``; its top follows only when the window would
   be taller than ``max_height`` (a window that grows, then travels); a travelling window
   keeps a chimney, a column of ``chimney`` cone radii about the axis up to the free
   surface (:meth:`MovingWindowPenetration._window_shape`, a :class:`~coupling.regions.
   Union` of two boxes);
2. surviving grains get reference positions ``X = x - u(X)`` (fixed point: a ghost stays
   exactly where it is, a free grain's displacement ``x - X`` is the FE displacement there,
   so the first projection after the move returns the FE's own values); grains heaved
   beyond the mesh keep X clamped inside it and their motion is counted from ``x - u(X)``
   (``x_base``), so that they do not jump;
3. the newly covered region (inside the new window + ghost band, outside the old one) is
   filled, in 2D, with the initial window's own hexagonal lattice continued downward in
   phase (:func:`continued_lattice`: the new rows nest in the notches of the old band's
   rows and of the ghosts beside them, so the grains above rest on them from the start; a
   lattice laid afresh at the measured fraction left a gap of up to a row at the seam and
   took almost no load); in 3D with a jittered fcc lattice at the packing fraction
   measured in the current window away from the cone. Radii come from the same
   distribution; each new grain is placed at ``X + u(X)`` with the FE velocity and spin
   ``d phi / dt``; new grains overlapping old ones by more than half a radius are dropped,
   the rest are pushed apart geometrically with the old grains held;
4. grains now outside window + band are removed: far behind the tip and away from the shaft
   their motion is the continuum's (the FE underneath carries it from here on); with
   ``chimney = 0`` the shaft passes through continuum without contact above the window
   (the sleeve friction there is lost);
5. kinds are re-assigned from the new window and the DEM ``Simulation`` is rebuilt with the
   contact history of surviving pairs carried over;
6. the grains are generated to the local stress state: for ``settle_steps`` DEM steps the
   ghosts stay at the FE positions, the cone is paused and the old grains near it are held
   (left free they would relax away from the tip); the generated free grains (the new ones
   and the old bottom band's, a lattice that was held and never settled) settle under
   gravity for the first half, then each layer's radii are grown by a servo
   (:func:`servo_growth`, at most ``servo_rate`` per cycle) until its Love-Weber axial
   stress is the target: the stress of the free grains just above the old bottom plus the
   weight between the two layers, its other parts scaled with it (vertical equilibrium of
   the window's column, :meth:`MovingWindowPenetration._target`, which says why the FE +
   geostatic stress is not used). ``move_records`` holds the new grains' stress against
   that target (``mismatch_vs_layer_above``) and against the FE stress plus the geostatic
   overburden ``rho g h`` (``mismatch_vs_fe_plus_geostatic``, a cross-check), and the
   servo's trace;
7. the settle is part of the generation: the generated grains' reference positions are
   solved again at their settled places (``X = x - u(X)``), then the ``CouplingInterface``
   is rebuilt (its Dirichlet condition replaced, prescribed values taken from the current
   FE state) and the time stepper with the FE state, velocity and acceleration copied;
8. dofs the move released (prescribed before, free now: continuum behind the tip) carry the
   grains' flow, no elastic equilibrium: their out-of-balance force goes into a load ``f0``
   (:meth:`MovingWindowPenetration._release`), so the continuum starts from the state the
   grains left instead of springing back.

In 3D the continuum carries gravity and the geostatic confinement: the settled grains'
reference positions are solved against that state at the start (``X + u_geo(X) = x``) and
the coupling counts total displacements from there.
"""

from __future__ import annotations

import time

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem

from coupling.apps.penetration.coupled import (
    CoupledPenetration,
    cone_clump,
    cone_parts,
    cone_record,
    penetrator_clump,
)
from coupling.apps.penetration.parameters import MovingWindowParameters, PenetrationParameters
from coupling.locate import owner_ranks
from coupling.operators import FieldBasis
from coupling.regions import Box, CouplingRegions, Union
from coupling.substep import GhostMotion, sub_cycle
from dem import GHOST, Particles, Simulation, build_pairs
from dem.bonded import hexagonal_lattice
from dem.neighbours import carry_history
from dem.packing import push_apart
from dem.stress import contact_points, love_weber_stress
from granfe.dynamics import GeneralizedAlpha
from granfe.forms import internal_work

__all__ = ["MovingWindowParameters", "MovingWindowPenetration", "tip_near_bottom", "moved_window",
           "lattice_fill", "continued_lattice", "push_apart", "field_at", "reference_positions",
           "carry_pair_history", "fe_stress_average", "isotropic_modulus", "servo_growth",
           "scale_radii", "refined_depth"]


# ---- geometry of a move ------------------------------------------------------------------
def tip_near_bottom(tip: float, window: Box, distance: float, axis: int = -1) -> bool:
    """True when the tip coordinate along ``axis`` is within ``distance`` [m] of the
    window's bottom face (or below it)."""
    if not distance >= 0:
        raise ValueError(f"distance must be >= 0 m, got {distance!r}")
    return bool(tip - window.lo[axis] <= distance)


def moved_window(window: Box, step: float, max_height: float | None = None, axis: int = -1) -> Box:
    """The window with its bottom ``step`` [m] lower along ``axis``; the top follows only as
    far as needed to keep the height <= ``max_height`` [m]."""
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step must be > 0 m, got {step!r}")
    lo, hi = list(window.lo), list(window.hi)
    lo[axis] -= step
    if max_height is not None:
        hi[axis] = min(hi[axis], lo[axis] + max_height)
    return Box(tuple(lo), tuple(hi))


def _mean_measure(radius, jitter, dim):
    """E[pi r^2] (2D) or E[4/3 pi r^3] (3D) for r = radius (1 - jitter U), U uniform."""
    j = jitter
    if dim == 2:
        return np.pi * radius**2 * (1 - j + j**2 / 3)
    return 4 / 3 * np.pi * radius**3 * (1 - 1.5 * j + j**2 - j**3 / 4)


def lattice_fill(lo, hi, radius: float, jitter: float, fraction: float, rng):
    """A jittered lattice in the box [lo, hi] (2 or 3 entries) at solid ``fraction``.

    Radii are ``radius (1 - jitter U)`` as in the initial window; the spacing s of the
    hexagonal (2D) or fcc (3D) lattice gives the expected fraction. Each centre moves
    uniformly inside a ball of its free gap ``(s - 2 r) / 2`` (none when s < 2 r: those
    overlaps are for :func:`push_apart`). Returns X (n, 3), r (n,).
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    dim = lo.size
    if not 0 < fraction < (0.9069 if dim == 2 else 0.7405):
        raise ValueError(f"fraction must lie in (0, densest lattice packing), got {fraction!r}")
    if np.any(hi <= lo):
        return np.zeros((0, 3)), np.zeros(0)
    cell = np.sqrt(3) / 2 if dim == 2 else 1 / np.sqrt(2)  # volume per site / s^dim
    s = (_mean_measure(radius, jitter, dim) / (fraction * cell)) ** (1 / dim)
    if dim == 2:
        rows = np.arange(lo[1] + 0.5 * s, hi[1] - 0.5 * s + 1e-12 * s, s * np.sqrt(3) / 2)
        pts = [np.column_stack([xs, np.full_like(xs, y)]) for k, y in enumerate(rows)
               for xs in [np.arange(lo[0] + 0.5 * s * (1 + k % 2), hi[0] - 0.5 * s + 1e-12 * s, s)]]
    else:
        a = s * np.sqrt(2)
        base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
        ranges = [np.arange(lo[k] + 0.5 * s, hi[k] - 0.5 * s + 1e-12 * s, a) for k in range(3)]
        corners = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, 3)
        pts = [(corners[:, None] + base[None]).reshape(-1, 3)]
        pts = [q[np.all(q <= hi - 0.5 * s + 1e-12 * s, axis=1)] for q in pts]
    X = np.vstack(pts) if pts else np.zeros((0, dim))
    r = radius * (1 - jitter * rng.random(len(X)))
    d = rng.normal(size=X.shape)
    d /= np.linalg.norm(d, axis=1)[:, None]
    amp = np.maximum(0.5 * s - r, 0.0) * rng.random(len(X)) ** (1 / dim)
    out = np.zeros((len(X), 3))
    out[:, :dim] = X + d * amp[:, None]
    return out, r


def continued_lattice(lo, hi, origin, radius: float, jitter: float, rng):
    """The hexagonal lattice of touching disks of ``radius`` that
    :func:`dem.bonded.hexagonal_lattice` lays from ``origin`` (2,), continued over the box
    [lo, hi] (2D), radii reduced by up to ``jitter`` as in the initial window.

    Rows below the origin keep the lattice's phase (its period along the axis is two rows,
    sqrt(3) d): new rows nest in the notches of the old ones and of the ghost bands beside
    them, so the grains above rest on them from the start. Returns X (n, 3), r (n,).
    """
    lo, hi, origin = (np.asarray(a, float)[:2] for a in (lo, hi, origin))
    period = np.sqrt(3) * 2 * radius
    y0 = origin[1] - np.ceil((origin[1] - lo[1]) / period) * period
    X = hexagonal_lattice((origin[0], y0), hi, radius)
    X = X[np.all((X[:, :2] >= lo) & (X[:, :2] <= hi), axis=1)]
    return X, radius * (1 - jitter * rng.random(len(X)))


# ---- FE values at points -----------------------------------------------------------------
def field_at(V, w: fem.Function, points: np.ndarray, sub: int) -> np.ndarray:
    """Values (n, value_size) of field ``sub`` (0: u, 1: phi) of ``w`` at ``points`` (n, >=
    gdim), on every rank; the same basis evaluation as the coupling's ghost motion.
    Collective."""
    gdim = V.mesh.geometry.dim
    pts = np.asarray(points, float)[:, :gdim]
    owners = owner_ranks(V.mesh, pts)
    mine = np.flatnonzero(owners == V.mesh.comm.rank)
    basis = FieldBasis.build(V, pts[mine], sub=sub)
    local = basis.interpolate(w)
    out = np.zeros((len(pts), basis.value_size))
    for idx, val in V.mesh.comm.allgather((mine, local)):
        out[idx] = val.reshape(len(idx), basis.value_size)
    return out


def reference_positions(x: np.ndarray, displacement, start: np.ndarray | None = None,
                        clamp=None, tolerance: float = 1e-14, iterations: int = 100):
    """Solve ``X + u(X) = x`` for X (n, 3) from ``start`` (default x).

    Relaxed fixed point ``X <- clamp(X + b (x - u(X) - X))`` per point, ``b = 1`` (rate: the
    displacement gradient) halved for a point whose residual grows (large gradients at
    the tip). ``displacement`` maps points (n, 3) to (n, gdim) [m]; ``clamp`` keeps the
    iterates where u is defined (grains heaved above the continuum's surface get the
    nearest point of the mesh's box: for them ``X + u(X) != x``).

    Returns X and the residual |x - X - u(X)| (n,) [m] of the last iterate.
    """
    X = (x if start is None else start).copy()
    n = len(x)
    beta, res_prev = np.ones(n), np.full(n, np.inf)
    scale = max(float(np.abs(x).max(initial=0.0)), 1e-300)
    res = np.zeros(n)
    for _ in range(iterations):
        r = x - X
        u = displacement(X)
        r[:, : u.shape[1]] -= u
        res = np.linalg.norm(r, axis=1)
        if np.all(res <= tolerance * scale):
            break
        beta = np.where(res > res_prev, 0.5 * beta, beta)
        res_prev = res
        new = X + beta[:, None] * r
        X = clamp(new) if clamp is not None else new
    return X, res


def carry_pair_history(old_nl, new_of_old: np.ndarray, new_nl) -> int:
    """Copy tangential springs, slip flags and spring energies of surviving pairs from the
    neighbour list ``old_nl`` to ``new_nl`` (already built); ``new_of_old`` maps old
    particle indices to new ones (-1: removed). Index order is kept, so (i < j) pairs stay
    (i < j) and the springs keep their sign. Returns the number of pairs carried."""
    ni, nj = new_of_old[old_nl.pi], new_of_old[old_nl.pj]
    alive = (ni >= 0) & (nj >= 0)
    if np.any(ni[alive] >= nj[alive]):
        raise ValueError("new_of_old must keep the particles' order")
    keys = ni[alive] * new_nl.n + nj[alive]
    order = np.argsort(keys)
    new_keys = new_nl.pi * new_nl.n + new_nl.pj
    new_nl.hist, new_nl.slip, new_nl.etan = carry_history(
        keys[order], new_keys, old_nl.hist[alive][order], old_nl.slip[alive][order],
        old_nl.etan[alive][order])
    return int(np.isin(new_keys, keys).sum())


def fe_stress_average(problem, lo, hi) -> np.ndarray:
    """Force stress sigma (gdim, gdim) [Pa] of ``problem.w`` averaged over the cells whose
    midpoints lie in the box [lo, hi] (reference coordinates). Collective."""
    from dolfinx.mesh import compute_midpoints

    domain = problem.domain
    tdim, gdim = domain.topology.dim, domain.geometry.dim
    n_cells = domain.topology.index_map(tdim).size_local
    mid = compute_midpoints(domain, tdim, np.arange(n_cells, dtype=np.int32))[:, :gdim]
    chi = fem.Function(fem.functionspace(domain, ("DG", 0)))
    inside = np.all((mid >= np.asarray(lo)[:gdim]) & (mid <= np.asarray(hi)[:gdim]), axis=1)
    chi.x.array[:n_cells] = inside
    chi.x.scatter_forward()
    sigma, _ = problem.stress_expressions()
    comm = domain.comm
    area = comm.allreduce(fem.assemble_scalar(fem.form(chi * problem.dx)), MPI.SUM)
    if area <= 0:
        raise ValueError(f"no cell midpoint lies in the box {lo}..{hi}")
    return np.array([[comm.allreduce(fem.assemble_scalar(fem.form(sigma[i, j] * chi * problem.dx)),
                                     MPI.SUM) / area for j in range(gdim)] for i in range(gdim)])


def refined_depth(prm: PenetrationParameters, mv: MovingWindowParameters) -> float:
    """Depth [m] down to which the chamber is meshed at the window's element size: the
    deepest bottom the window can reach (the tip at ``mv.depth`` with the window moved
    ``step`` below the trigger distance, and one step to spare). Coarse elements under a
    window that moved out of the refined zone hold few grains per node: the projection and
    the ghosts then feed each other until the ghost band breaks apart (measured in
    ``benchmarks/moving_window.py``). Raises ValueError naming
    ``chamber_depth`` when the chamber is too shallow for it."""
    reach = mv.depth + (mv.trigger + 2 * mv.step) * 2 * prm.radius
    if reach + (prm.ghost_width + 1) * 2 * prm.radius >= prm.chamber_depth:
        raise ValueError(f"chamber_depth = {prm.chamber_depth} m is too shallow for a window "
                         f"that follows the cone to depth = {mv.depth} m (its bottom reaches "
                         f"{reach:.3g} m, plus the ghost band): deepen the chamber or lower "
                         f"the depth, trigger or step")
    return max(prm.window_depth, reach)


# ---- stress of the grains being generated ---------------------------------------------------
def isotropic_modulus(material, dim: int) -> float:
    """D sigma_mean / d e [Pa] of the continuum under the isotropic strain ``e I``:
    ``dim lam + 2 mu + kappa`` (the micropolar rotation is not strained by it)."""
    return dim * material.lam + 2 * material.mu + material.kappa


def servo_growth(stress: float, target: float, modulus: float, rate: float) -> float:
    """Relative radius change (clipped to +-``rate``) that moves a packing's axial stress
    ``stress`` toward ``target`` (both tension-positive) [Pa].

    Growing every radius by ``e`` in a held container strains the packing like ``-e I``,
    which changes its stress by about ``-modulus e`` (:func:`isotropic_modulus` of the
    continuum, whose constants come from the same contacts). A packing still short of
    contacts is softer: the clip then closes its gaps a little per cycle while gravity
    rearranges it, rather than in one jump that would overlap the grains already touching.
    """
    return float(np.clip((stress - target) / modulus, -rate, rate))


def scale_radii(p: Particles, index: np.ndarray, factor: float) -> None:
    """Radii of particles ``index`` times ``factor``; their masses and inertias follow at
    the same density (disks of unit thickness in 2D: m ~ r^2, I ~ r^4; spheres r^3, r^5)."""
    p.radius[index] *= factor
    p.mass[index] *= factor**p.dim
    p.inertia[index] *= factor ** (p.dim + 2)


# ---- the coupled penetration with a moving window -------------------------------------------
class MovingWindowPenetration(CoupledPenetration):
    """:class:`CoupledPenetration` whose DE window follows the tip (module docstring).

    ``prm.depth`` is what the initial window allows (it sizes nothing else); the run goes to
    ``moving.depth``. ``moves`` holds one record per move.
    """

    def __init__(self, prm: PenetrationParameters, moving: MovingWindowParameters, comm, log=print):
        if prm.interface != "loose":
            raise ValueError(f"interface = {prm.interface!r}: a window that follows the penetrator "
                             "exchanges loosely (interface = 'loose') so far")
        if prm.vertical_stress > 0 or prm.lateral != "rigid":
            raise ValueError("a window that follows the penetrator is built for a free surface "
                             "under gravity with rigid sides (vertical_stress = 0, lateral = 'rigid') so far: its "
                             "new grains are not consolidated under a surcharge")
        self.moving = moving   # before the parent's set-up: it sizes the mesh (_refined_depth)
        super().__init__(prm, comm, log=log)
        # where the initial window's lattice starts (coupling.apps.penetration.coupled: window + band)
        self._lattice_origin = np.array(self.regions.window.lo) - self.regions.ghost_width
        self.axis = self.sim.p.dim - 1
        self._wide, self._top0 = self.regions.window, self.regions.window.hi[self.axis]
        self.x_base = self.x_ref.copy()   # grains where the continuum is undeformed (_base)
        self.depth = 0.0
        self.moves: list[dict] = []
        self._stepper_count = 0
        self._g_prev = None      # the ghosts' motion the last FE step drove the grains to
        # a shaft long enough for the whole run (the parent sized it for prm.depth)
        rc = prm.cone_radius
        if prm.dim == 2:
            pen, r_pen, on_cone = cone_clump(rc, prm.apex_deg, moving.depth + 3 * rc, prm.radius)
        else:
            pen, r_pen, on_cone = penetrator_clump(prm, moving.depth + 3 * rc)
        pen[:, self.axis] += self.pen0[:, self.axis].min() - pen[:, self.axis].min()
        self.pen0, self.on_cone, self._r_pen = pen, on_cone, r_pen
        self.parts = cone_parts(pen, on_cone, prm)
        clump = Particles.spheres(pen, r_pen, prm.density, dim=self.sim.p.dim, kind=GHOST)
        self.clump_internal = Simulation(clump, self.material, allow_overlap=True).p.force.copy()
        p, n = self.sim.p, self.n_grains
        self._rebuild_simulation(p.x[:n], p.v[:n], p.omega[:n], p.radius[:n], self.kinds,
                                 np.arange(n), same_clump=False)
        if prm.dim == 3:
            # the FE holds the geostatic state (the grains settled into it): the grains'
            # reference positions solve X + u(X) = x with u = w_geo, and the coupling counts
            # the total displacement from there (no separate w_geo offsets as in the parent)
            x = self.sim.p.x[:n]
            self.x_ref, _ = reference_positions(x, self._displacement, clamp=self._clamp)
            self.x_base = self._base(x, self.x_ref)
        # the load that keeps released dofs where the grains left them (_release), in the
        # forms of the stepper built next
        self._f0 = fem.Function(self.problem.V, name="release_load")
        f0_u, f0_phi = ufl.split(self._f0)
        self.problem.body_force(f0_u)
        self.problem.body_couple(f0_phi)
        self._mass_solver = None
        self._rebuild_coupling()

    def _refined_depth(self) -> float:
        return refined_depth(self.prm, self.moving)

    @property
    def n_steps(self) -> int:
        return int(np.ceil(self.moving.depth / self.prm.velocity / self.dt_fe))

    # ---- state --------------------------------------------------------------------------
    def tip(self) -> float:
        """Lowest point of the cone along the axis [m] (current configuration)."""
        p = self.sim.p
        return float((p.x[self.pen_index, self.axis] - p.radius[self.pen_index]).min())

    def needs_move(self) -> bool:
        d = 2 * self.prm.radius
        # the tip moves with the cone; the window lives in reference coordinates, and
        # the FE displacement under the tip is small against the trigger distance
        return (len(self.moves) < self.moving.max_moves
                and tip_near_bottom(self.tip(), self.regions.window, self.moving.trigger * d, self.axis))

    def _displacement(self, X):
        return field_at(self.problem.V, self.problem.w, X, 0)

    def _base(self, x, X):
        """Where grains at x (n, 3) with reference positions X are when the continuum is
        undeformed: ``x - u(X)``, which is X itself where :func:`reference_positions`
        converged. A grain heaved beyond the mesh has its X clamped inside it; its ghost
        motion ``N(X) (w - w_old)`` is added to this base instead of to X, or it would jump
        by the residual at the first step after the move."""
        base = np.array(x, float, copy=True)
        base[:, : self.sim.p.dim] -= self._displacement(X)
        return base

    def _clamp(self, X):
        """Points moved into the chamber's box (a hair inside, so that a cell holds them)."""
        g, dim = self.problem.domain.geometry.x, self.sim.p.dim
        lo = np.ascontiguousarray(g[:, :dim].min(axis=0, initial=np.inf))
        hi = np.ascontiguousarray(g[:, :dim].max(axis=0, initial=-np.inf))
        self.comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        self.comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
        eps = 1e-9 * float(np.max(hi - lo))
        out = X.copy()
        out[:, :dim] = np.clip(X[:, :dim], lo + eps, hi - eps)
        return out

    def _rebuild_simulation(self, x, v, omega, radius, kinds, new_of_old, same_clump=True):
        """A new Simulation of grains (x, v, omega, radius (n,), kinds 0/1) + the cone at the
        current depth, carrying the contact history of surviving pairs (``new_of_old`` over
        the old grains, -1: removed; the cone's disks map onto themselves if
        ``same_clump``). Returns the number of contacts carried."""
        prm, old = self.prm, self.sim
        n, n_pen = len(x), len(self.pen0)
        pen_x = self.pen0 - self.depth * np.eye(3)[self.axis]
        kind = np.concatenate([np.where(kinds == 1, GHOST, 0), np.full(n_pen, GHOST)])
        p = Particles.spheres(np.vstack([x, pen_x]), np.concatenate([radius, np.full(n_pen, self._r_pen)]),
                              prm.density, dim=old.p.dim, kind=kind.astype(np.int8),
                              v=np.vstack([v, np.zeros((n_pen, 3))]),
                              omega=np.vstack([omega, np.zeros((n_pen, 3))]))
        sim = Simulation(p, self.material, gravity=old.gravity, dt=old.dt, allow_overlap=True, skin=old.nl.skin)
        old_pen = len(self.pen_index)
        cone = n + np.arange(old_pen) if same_clump else np.full(old_pen, -1)
        carried = carry_pair_history(old.nl, np.concatenate([np.asarray(new_of_old, np.int64), cone]),
                                     sim.nl)
        sim.compute_forces(update_history=False)   # forces of the first kick with the history
        self.sim = sim
        self.kinds = np.asarray(kinds, np.int8)
        self.n_grains = n
        self.pen_index = np.arange(n, n + n_pen)
        self.free_local = np.flatnonzero(self.kinds == 0)
        self.ghost_local = np.flatnonzero(self.kinds == 1)
        return carried

    # ---- measures -----------------------------------------------------------------------
    def _energies(self) -> dict:
        """Kinetic energy of the free grains and elastic energy of all contacts [J]."""
        sim = self.sim
        elastic = sim.compute_forces(update_history=False)[0]
        return {"kinetic": float(sim.kinetic_energy().sum()), "elastic": float(elastic)}

    def _tip_force(self) -> float:
        """Axial force of the grains on the cone part [N] (after :meth:`_energies`)."""
        f = self.sim.p.force[self.pen_index] - self.clump_internal
        return float(f[self.on_cone, self.axis].sum())

    def _box(self, axis_lo, axis_hi, lateral_margin=0.0):
        """(lo, hi) of the window's lateral extent (widened by a margin) x [axis_lo, axis_hi]."""
        lo, hi = list(self.regions.window.lo), list(self.regions.window.hi)
        lo = [v - lateral_margin for v in lo]
        hi = [v + lateral_margin for v in hi]
        lo[self.axis], hi[self.axis] = axis_lo, axis_hi
        return np.array(lo), np.array(hi)

    def _grain_stress(self, lo, hi) -> np.ndarray:
        """Love-Weber stress (dim, dim) [Pa] of the contacts whose points lie in [lo, hi]."""
        p, dim = self.sim.p, self.sim.p.dim
        # ghost-ghost pairs count: a band of ghosts carries the weight above it too
        pairs, force = self.sim.contact_forces(skip_ghost_pairs=False)
        cone = np.isin(pairs, self.pen_index).all(axis=1)
        pairs, force = pairs[~cone], force[~cone]
        if len(pairs) == 0:
            return np.zeros((dim, dim))
        xc = contact_points(p.x, p.radius, pairs)[:, :dim]
        mask = np.all((xc >= lo) & (xc <= hi), axis=1)
        return love_weber_stress(p.x, pairs, force, float(np.prod(hi - lo)), mask)[:dim, :dim]

    def _packing_fraction(self) -> float:
        """Solid fraction of the grains in the current window below the surface, away from
        the cone (a strip of two cone radii either side of the axis left out)."""
        d, ax, dim = 2 * self.prm.radius, self.axis, self.sim.p.dim
        # the ghost band belongs to the same packing: include it for a larger sample
        # (below the top of the full-width part: above it only the chimney holds grains)
        lo, hi = self._box(self.regions.window.lo[ax] - self.regions.ghost_width,
                           min(self.surface - 2 * d, self._wide.hi[ax]),
                           lateral_margin=self.regions.ghost_width)
        X = self.x_ref[:, :dim]
        lateral = [k for k in range(dim) if k != ax]
        strip = 2 * self.prm.cone_radius
        inside = np.all((X >= lo) & (X <= hi), axis=1) & (np.linalg.norm(X[:, lateral], axis=1) > strip)
        r = self.sim.p.radius[: self.n_grains][inside]
        measure = np.pi * r**2 if dim == 2 else 4 / 3 * np.pi * r**3
        cross = np.prod((hi - lo)[lateral]) - (2 * strip if dim == 2 else np.pi * strip**2)
        return float(measure.sum() / (cross * (hi - lo)[ax]))

    # ---- the window's shape ------------------------------------------------------------
    def _window_shape(self, wide: Box):
        """The window for the full-width box ``wide``: itself while its top is the initial
        window's (above the free surface), else with a chimney, the column of ``chimney``
        cone radii about the axis from ``wide`` up to that top, added.

        Converting the grains behind the tip back to continuum across the whole width put a
        ghost band on top of them that follows the FE, which moves elastically: the heave the
        cone drives around its shaft pressed the grains against a lid that does not yield
        (tip resistance 2-5x that of a window that only grows). Without any top (the grains
        above removed, their weight put on the top rows), the free grains' heave, projected
        into the FE, lifted the ghosts under them, which lifted the grains: the window rose
        by 20 mm within 15 mm of penetration. The chimney keeps the free surface around the
        shaft (the heave and the sleeve friction stay grain-scale) and converts the grains
        behind the tip and away from the shaft, where the continuum is a fair model.
        """
        ax, c = self.axis, self.moving.chimney * self.prm.cone_radius
        if c <= 0 or wide.hi[ax] >= self._top0:
            return wide
        lo, hi = [-c] * len(wide.lo), [c] * len(wide.lo)
        lo[ax], hi[ax] = wide.lo[ax], self._top0
        return Union((wide, Box(tuple(lo), tuple(hi))))

    # ---- the move -----------------------------------------------------------------------
    def _new_grains(self, old: CouplingRegions, new: CouplingRegions, fraction, rng):
        """Reference centres (k, 3) and radii of the lattice filling new minus old coverage."""
        prm, ax, dim = self.prm, self.axis, self.sim.p.dim
        band = new.ghost_width
        lo, hi = np.array(new.window.lo) - band, np.array(new.window.hi) + band
        hi[ax] = min(old.window.lo[ax], hi[ax])
        if dim == 2:
            X, r = continued_lattice(lo, hi, self._lattice_origin, prm.radius, prm.jitter, rng)
        else:
            X, r = lattice_fill(lo, hi, prm.radius, prm.jitter, fraction, rng)
        keep = (old.particle_kinds(X[:, :dim]) < 0) & (new.particle_kinds(X[:, :dim]) >= 0)
        return X[keep], r[keep]

    def move(self) -> dict:
        """Move the window one step and convert continuum <-> grains (module docstring).
        Collective (FE evaluations); every rank does the same DEM work."""
        t0 = time.perf_counter()
        prm, mv, ax, dim = self.prm, self.moving, self.axis, self.sim.p.dim
        d, n = 2 * prm.radius, self.n_grains
        p = self.sim.p
        before = self._energies()
        force_before = self._tip_force()
        old_regions = self.regions
        old_lo = old_regions.window.lo[ax]
        band = old_regions.ghost_width
        # the layer the new grains will carry: the free grains just above the old bottom
        ref_lo, ref_hi = self._box(old_lo, old_lo + band)
        stress_layer_before = self._grain_stress(ref_lo, ref_hi)
        wide = moved_window(self._wide, mv.step * d, mv.max_height, ax)
        if wide.hi[ax] > self.surface - band and wide.hi[ax] < self._top0:
            # a top band among the heaved grains would act as a lid on them: not yet
            hi = list(wide.hi)
            hi[ax] = self._top0
            wide = Box(wide.lo, tuple(hi))
        regions = CouplingRegions(self._window_shape(wide), band, old_regions.handshake)
        self._wide = wide
        # ---- survivors: reference positions from the current FE field, kinds in the new window
        X_old, res_old = reference_positions(p.x[:n], self._displacement, start=self.x_ref,
                                             clamp=self._clamp)
        kinds_old = regions.particle_kinds(X_old[:, :dim])
        # a ghost follows the continuum at its reference position: one heaved beyond the
        # mesh (X clamped, unresolved) would hang on the continuum's free surface
        kinds_old[(kinds_old == 1) & (res_old > 1e-9)] = -1
        keep = np.flatnonzero(kinds_old >= 0)
        base_old = self._base(p.x[:n], X_old)
        # ---- new grains: lattice in the reference configuration, mapped by the FE fields
        fraction = self._packing_fraction()
        rng = np.random.default_rng(mv.seed + len(self.moves))
        X_new, r_new = self._new_grains(old_regions, regions, fraction, rng)
        x_new = X_new.copy()
        x_new[:, :dim] += self._displacement(X_new)
        # ---- overlaps with the grains kept and the cone: drop deep ones, push the rest apart
        x_held = np.vstack([p.x[keep], p.x[self.pen_index]])
        r_held = np.concatenate([p.radius[keep], p.radius[self.pen_index]])
        x_all, r_all = np.vstack([x_held, x_new]), np.concatenate([r_held, r_new])
        pi, pj = build_pairs(x_all, r_all, 0.0)
        ov = r_all[pi] + r_all[pj] - np.linalg.norm(x_all[pj] - x_all[pi], axis=1)
        nh = len(x_held)
        deep = (pi < nh) & (pj >= nh) & (ov > 0.5 * np.minimum(r_all[pi], r_all[pj]))
        drop = np.unique(pj[deep]) - nh
        alive = np.setdiff1d(np.arange(len(x_new)), drop)
        x_new, X_new, r_new = x_new[alive], X_new[alive], r_new[alive]
        movable = np.concatenate([np.zeros(nh, bool), np.ones(len(x_new), bool)])
        x_all, its, worst = push_apart(np.vstack([x_held, x_new]), np.concatenate([r_held, r_new]),
                                       movable, mv.overlap_tolerance * prm.radius, mv.relax_iterations)
        x_new = x_all[nh:]
        X_new, res_new = reference_positions(x_new, self._displacement, start=X_new,
                                             clamp=self._clamp)
        kinds_new = regions.particle_kinds(X_new[:, :dim])
        inside = kinds_new >= 0
        x_new, X_new, r_new, kinds_new = x_new[inside], X_new[inside], r_new[inside], kinds_new[inside]
        st = self.stepper
        v_new = np.zeros_like(x_new)
        v_new[:, :dim] = field_at(self.problem.V, st.v, X_new, 0)
        w_new = np.zeros_like(x_new)
        spin = field_at(self.problem.V, st.v, X_new, 1)
        if dim == 2:
            w_new[:, 2] = spin[:, 0]
        else:
            w_new[:] = spin
        # ---- the new DEM and coupling
        new_of_old = np.full(n, -1, np.int64)
        new_of_old[keep] = np.arange(len(keep))
        X_all, kinds_all = np.vstack([X_old[keep], X_new]), np.concatenate([kinds_old[keep], kinds_new])
        carried = self._rebuild_simulation(
            np.vstack([p.x[keep], x_new]), np.vstack([p.v[keep], v_new]),
            np.vstack([p.omega[keep], w_new]), np.concatenate([p.radius[keep], r_new]),
            kinds_all, new_of_old)
        self.x_ref = X_all
        self.x_base = np.vstack([base_old[keep], self._base(x_new, X_new)])
        self.regions = regions
        after_rebuild = self._energies()
        # ---- settle: ghosts at the FE positions, the cone paused, the generated grains (all
        # below the old bottom: the old band's too, a lattice never settled) grown to the target
        new_lo, new_hi = self._box(regions.window.lo[ax], old_lo - band if mv.step * d > band + d else old_lo)
        stress_new_before = self._grain_stress(new_lo, new_hi)
        generated = self.x_ref[:, ax] < old_lo
        # one servo per layer (the old band, then the new grains): the stress falls off
        # with the distance from the tip, a single growth would overload the upper layer
        groups = []
        for a, b in ((new_hi[ax], old_lo), (new_lo[ax], new_hi[ax])):
            if b > a:
                lo_g, hi_g = self._box(a, b)
                grains = np.flatnonzero(generated & (self.kinds == 0) & (self.x_ref[:, ax] >= a)
                                        & (self.x_ref[:, ax] < b))
                groups.append((grains, lo_g, hi_g,
                               self._target(stress_layer_before, ref_lo, ref_hi, lo_g, hi_g)))
        held, servo = self._settle(groups)
        after_settle = self._energies()
        stress_new = self._grain_stress(new_lo, new_hi)
        stress_layer_after = self._grain_stress(ref_lo, ref_hi)
        target_tensor = self._target(stress_layer_before, ref_lo, ref_hi, new_lo, new_hi)
        target = target_tensor[ax, ax]
        # the settle is part of the generation, not a motion of the continuum: the generated
        # grains' reference positions follow, so that the next projection finds the FE's values
        settled = self.sim.p.x[: self.n_grains][generated]
        self.x_ref[generated], res_settled = reference_positions(
            settled, self._displacement, start=self.x_ref[generated], clamp=self._clamp)
        self.x_base[generated] = self._base(settled, self.x_ref[generated])
        old_interface = self.interface
        self._rebuild_coupling()
        released = self._release(old_interface)
        sigma_fe = fe_stress_average(self.problem, new_lo, new_hi)
        centre = 0.5 * (new_lo[ax] + new_hi[ax])
        geostatic = -self.material_fe.rho * self.prm.gravity * (self.surface - centre)
        fe_geo = sigma_fe[ax, ax] + geostatic
        record = {
            "move": len(self.moves) + 1, "depth": self.depth, "tip": self.tip(),
            "window_lo_before": list(old_regions.window.lo), "window_hi_before": list(old_regions.window.hi),
            "window_lo": list(regions.window.lo), "window_hi": list(regions.window.hi),
            "created": int(len(x_new)), "removed": int(n - len(keep)),
            "dropped_overlapping": int(len(drop)), "push_apart_iterations": int(its),
            "overlap_left": worst,
            "reference_residual_max": {"survivors": float(res_old[keep].max(initial=0.0)),
                                       "new": float(res_new.max(initial=0.0)),
                                       "settled": float(res_settled.max(initial=0.0))},
            "reference_unresolved": int((res_old[keep] > 1e-9).sum()), "packing_fraction_target": fraction,
            "contacts_carried": carried, "held_in_settle": held, "released_dofs": released,
            "window_wide_hi": list(self._wide.hi), "grains": self.n_grains,
            "servo": servo,
            "energy_before": before, "energy_after_rebuild": after_rebuild,
            "energy_after_settle": after_settle,
            "tip_force_before": force_before, "tip_force_after_settle": self._tip_force(),
            "stress_axis": {
                "new_grains_before_settle": float(stress_new_before[ax, ax]),
                "new_grains_after_settle": float(stress_new[ax, ax]),
                "layer_above_before_move": float(stress_layer_before[ax, ax]),
                "layer_above_after_settle": float(stress_layer_after[ax, ax]),
                "target": float(target),
                "new_grains_lateral": float(np.trace(stress_new) - stress_new[ax, ax]) / (dim - 1),
                "target_lateral": float(np.trace(target_tensor) - target) / (dim - 1),
                "fe_increment": float(sigma_fe[ax, ax]), "geostatic": float(geostatic),
                "fe_plus_geostatic": float(fe_geo)},
            "stress_mean": {
                "new_grains_after_settle": float(np.trace(stress_new) / dim),
                "layer_above_before_move": float(np.trace(stress_layer_before) / dim)},
            "mismatch_vs_fe_plus_geostatic": float((stress_new[ax, ax] - fe_geo) / abs(fe_geo)),
            "mismatch_vs_layer_above": float((stress_new[ax, ax] - target)
                                             / max(abs(target), 1e-300)),
            "wall_time": time.perf_counter() - t0}
        self.moves.append(record)
        self.log(f"window move {record['move']} at depth {self.depth * 1e3:.1f} mm: bottom "
                 f"{old_lo * 1e3:.1f} -> {regions.window.lo[ax] * 1e3:.1f} mm, +{record['created']} "
                 f"-{record['removed']} grains ({self.n_grains}), settle: sigma_axis new "
                 f"{stress_new[ax, ax]:.3g} Pa vs target {target:.3g} Pa (layer above "
                 f"{stress_layer_before[ax, ax]:.3g} Pa, FE+geostatic {fe_geo:.3g} Pa) "
                 f"({record['wall_time']:.1f} s)")
        return record

    def _target(self, stress_above, above_lo, above_hi, lo, hi) -> np.ndarray:
        """Stress (dim, dim) [Pa] the grains in [lo, hi] must carry: the layer above's
        ``stress_above`` (dim, dim) with the weight between the two layers' centres added to
        its axial part, and its other parts scaled with it (the same stress ratio K).

        Vertical equilibrium of the window's column: a layer carrying less lets the grains
        above it sag (the shock of unloaded new grains). The cone's share spreads sideways
        with depth, but a line load keeps 87-99 % of itself within the window's width down
        to the new bottom in the demo's geometries (Flamant). The FE + geostatic stress is
        no target: while the window holds the free surface, the heave around the shaft,
        projected into the FE, lifts the whole continuum and its stress is tensile (+2 to
        +8 kPa down to the chamber's bottom), a state no cohesionless packing can take; once
        the window has left the surface, it agrees with this target within 15-35 % (demo)."""
        ax = self.axis
        dz = 0.5 * (above_lo[ax] + above_hi[ax] - lo[ax] - hi[ax])
        weight = self.material_fe.rho * self.prm.gravity * dz
        axial = stress_above[ax, ax]
        # the layer's stress ratio (isotropic if it carries nothing to take one from)
        ratio = stress_above / axial if axial < 0 else np.eye(len(stress_above))
        return ratio * (axial - weight)

    def _settle(self, groups=()):
        """``settle_steps`` DEM steps with ghosts, cone and the old grains near the cone held.

        ``groups`` holds (grains, lo, hi, target) of the free grains being generated: they
        settle under gravity for the first half; in the second, split into ``servo_cycles``
        parts, the radii of each group's grains are scaled before each part by
        :func:`servo_growth` toward the axial part of its ``target`` (dim, dim) [Pa], the
        stress of the contacts in its box [lo, hi] (the axial stress is what carries the
        grains above; the lateral one follows from the fabric the grains settled into and
        the held ghosts beside them). Returns how many free grains were held and the servo's
        trace per group (axial and mean stress [Pa], radius change per cycle)."""
        from scipy.spatial import cKDTree

        p, mv, sim, ax = self.sim.p, self.moving, self.sim, self.axis
        grow = np.concatenate([g[0] for g in groups] + [np.zeros(0, np.int64)]).astype(np.int64)
        # the grains being generated are not held: they are to form the packing under the tip
        old = np.setdiff1d(self.free_local, grow)
        dist, _ = cKDTree(p.x[self.pen_index]).query(p.x[old])
        near = old[dist < mv.settle_hold * 2 * self.prm.radius + self._r_pen]
        held = np.concatenate([self.ghost_local, near])
        p.v[held] = 0.0
        p.omega[held] = 0.0
        cycles = mv.servo_cycles if len(grow) and mv.servo_rate > 0 and mv.settle_steps > 0 else 0
        modulus = isotropic_modulus(self.material_fe, p.dim)
        traces = [{"target": np.asarray(t).tolist(), "grains": int(len(g)), "cycles": []}
                  for g, _, _, t in groups]
        kind = p.kind.copy()
        p.kind[near] = GHOST   # the integrator moves FREE particles only
        try:
            first = mv.settle_steps // 2 if cycles else mv.settle_steps
            sim.step(first)
            for n in np.diff(np.linspace(first, mv.settle_steps, cycles + 1).round().astype(int)):
                for (grains, lo, hi, target), trace in zip(groups, traces, strict=True):
                    sigma = self._grain_stress(lo, hi)
                    e = servo_growth(sigma[ax, ax], target[ax, ax], modulus, mv.servo_rate)
                    scale_radii(p, grains, 1 + e)
                    trace["cycles"].append({"stress_axis": float(sigma[ax, ax]), "growth": e,
                                            "stress_mean": float(np.trace(sigma)) / p.dim})
                # grown radii may reach pairs the Verlet skin did not list
                sim.rebuild_neighbours()
                sim.step(n)
        finally:
            p.kind[:] = kind
        return int(len(near)), traces

    def _release(self, old_interface) -> int:
        """Dofs prescribed before the move and free after it (the continuum that takes over
        from grains behind the tip) carry whatever the grains did there, a state that is no
        elastic equilibrium: left alone the continuum springs back within a few FE steps and
        its ghosts throw the grains beside the chimney out. The out-of-balance force
        ``r = K w - f`` at those dofs is added to the load ``f0`` (its Riesz representative,
        ``M_L2 f0 = r``) and their velocity and acceleration are zeroed, so that the state the
        grains left is where the continuum starts from, at rest (their flow stays a permanent
        deformation). The acceleration stays out of
        ``r``: at prescribed dofs it is the second difference of the relaxed projections,
        noise that, held as a load, drives surface nodes far off within a step.
        Returns the number of released dofs (all ranks). Collective."""
        from petsc4py import PETSc

        from dolfinx.fem.petsc import assemble_vector

        problem, st, comm = self.problem, self.stepper, self.comm
        before = np.concatenate([f.prescribed for f in old_interface.fields])
        after = np.concatenate([f.prescribed for f in self.interface.fields])
        released = np.setdiff1d(before, after)
        count = comm.allreduce(len(released), MPI.SUM)
        if count == 0:
            return 0
        V, c = problem.V, problem.constants
        du, dphi = ufl.TestFunctions(V)
        u, phi = ufl.split(problem.w)
        F = internal_work(u, phi, du, dphi, c) * problem.dx
        r = assemble_vector(fem.form(F - problem.external_work(du, dphi)))
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        keep = np.zeros(r.getLocalSize(), bool)
        keep[released] = True
        with r.localForm() as local:
            local.array[: len(keep)][~keep] = 0.0
        if self._mass_solver is None:
            from dolfinx.fem.petsc import assemble_matrix
            p, q = ufl.TrialFunction(V), ufl.TestFunction(V)
            M = assemble_matrix(fem.form(ufl.inner(p, q) * problem.dx))
            M.assemble()
            ksp = PETSc.KSP().create(comm)
            ksp.setOperators(M)
            ksp.setType("preonly")
            ksp.getPC().setType("lu")
            ksp.getPC().setFactorSolverType("mumps")
            self._mass_solver = (ksp, M)
        ksp, M = self._mass_solver
        df = M.createVecRight()
        ksp.solve(r, df)
        n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self._f0.x.array[:n_owned] += df.array_r[:n_owned]
        self._f0.x.scatter_forward()
        for rate in (st.v, st.a):
            rate.x.array[released] = 0.0
            rate.x.scatter_forward()
        for v in (r, df):
            v.destroy()
        return int(count)

    def _rebuild_coupling(self):
        """Interface and stepper for the current grains; the FE state carries on."""
        problem, old = self.problem, self.stepper
        problem.bcs[:] = [bc for bc in problem.bcs if bc is not self.interface.bc]
        iface = self._displacement_interface()
        w = problem.w.x.array
        iface.set_prescribed(np.concatenate([w[f.prescribed] for f in iface.fields]))
        self._stepper_count += 1
        st = GeneralizedAlpha(problem, float(old.dt.value), rho_inf=old.params.rho_inf,
                              prefix=f"{problem.prefix}mw{self._stepper_count}_")
        for name in ("w_old", "v", "a"):
            getattr(st, name).x.array[:] = getattr(old, name).x.array
        st.t = old.t
        self.interface, self.stepper = iface, st

    # ---- the run ------------------------------------------------------------------------
    def run(self, progress=None):
        """Push the cone to ``moving.depth``, moving the window whenever the tip nears its
        bottom. The coupled step is the parent's (ghosts from the FE, projection, SNES)."""
        while len(self.history) < self.n_steps:
            self.advance()
            if progress is not None:
                progress(self.history[-1])
        return self.history

    def advance(self) -> dict:
        """One FE step on the current window, moved first if the tip nears its bottom."""
        if self._g_prev is None:
            self._g_prev = self.interface.ghost_motion()
        if self.needs_move():
            self.move()
            self._g_prev = self.interface.ghost_motion()
        self._g_prev = self._coupled_step(len(self.history), self._g_prev)
        return self.history[-1]

    def _coupled_step(self, k, g_prev):
        """One FE step of :meth:`CoupledPenetration.run` on the current window."""
        prm, sim, iface, st = self.prm, self.sim, self.interface, self.stepper
        p, t0 = sim.p, time.perf_counter()
        g_next = iface.ghost_motion()
        st.predict()
        ghosts = GhostMotion(self.ghost_local, self.x_base[self.ghost_local], g_prev[0], g_next[0],
                             self.dt_fe)
        self.depth = sub_cycle(sim, prm.substeps, (self.pen_index, self.pen0), self.depth,
                               prm.velocity, self.axis, ghosts)
        n = self.n_grains
        n_u = iface.fields[0].prescribed.size
        old = iface.prescribed_values()
        D = old.copy()        # phi stays the FE's own (grain spins are not a displacement field)
        D[:n_u] = iface.project_displacement(p.x[:n, : self.axis + 1] - self.x_base[:, : self.axis + 1])
        iface.set_prescribed(old + prm.relaxation * (D - old))
        st.solve()
        st.finish()
        g_new = iface.ghost_motion()
        mismatch = self._check_ghosts(g_new, g_next, k)
        f = p.force[self.pen_index] - self.clump_internal
        self.history.append(cone_record(prm, f, self.parts, self.depth, k + 1, st.t,
                                        interface_mismatch=mismatch, grains=self.n_grains,
                                        window_bottom=self.regions.window.lo[self.axis],
                                        moves=len(self.moves), wall_time=time.perf_counter() - t0))
        return g_next
