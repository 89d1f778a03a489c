"""Coupled penetration: a DE window of frictional grains around a rigid penetrator pushed at
constant velocity, inside a micropolar FE chamber, joined through an overlap band. 2D plane
strain (a cone's section, per unit thickness) or 3D (a 60 degree cone or a flat-ended pile).

Set-up:

1. the FE chamber is meshed with gmsh, refined toward the window: in 2D the box
   ``[-W/2, W/2] x [-H, 0]``, in 3D the cylinder of diameter W and depth H about the z axis
   (:mod:`meshes.penetration`);
2. grains fill the window (a box: ``|x| <= a`` in 2D, ``|x|, |y| <= a`` in 3D, depth b) and
   its ghost band on a jittered lattice (hexagonal disks in 2D, fcc spheres in 3D, radii
   reduced by up to ``jitter``) and settle under gravity with the band's grains held (they
   are the ghosts: the container);
3. the continuum takes the settled packing's stiffness and density:

   - 2D (linear contacts of unit thickness): the bonded hexagonal-lattice constants of
     :func:`dem.bonded.hexagonal_lattice_micropolar` for (kn, kt) scaled by the coordination
     number over 6; the FE models the increment from the geostatic state (no gravity on the
     FE side, lateral sides on rollers);
   - 3D (Hertz-Mindlin spheres): the affine (Voigt) estimate of an isotropic packing of
     solid fraction ``phi``, coordination ``Z`` and mean radius ``R`` whose contacts have the
     mean tangent stiffnesses ``kn = 2 E* sqrt(R* delta)``, ``kt = 8 G* sqrt(R* delta)`` at
     the settled overlaps (branch vectors ``2 R n``, ``<n n n n>`` isotropic)::

         A = 3 phi Z / (2 pi R),  lam = mu = A (kn - kt) / 15,  kappa = A kt / 3,
         gamma = A kr / 3 with a rolling stiffness kr = 0.1 kt d^2 (as in 2D),

     i.e. the bulk modulus ``phi Z kn / (6 pi R)`` and the classical shear modulus
     ``mu + kappa / 2 = phi Z (2 kn + 3 kt) / (20 pi R)`` (Walton 1987, Chang & Misra 1990);
     the FE carries the total state: gravity ``rho g`` and, on the chamber's lateral
     boundary, the confining traction ``K0 rho g (s - z)`` with ``K0 = lam / (lam + 2 mu +
     kappa)``, the uniaxial-strain (geostatic) state the grains settled into inside their
     held container. That state ``w_geo`` is solved statically first; ghosts then follow
     ``N (w - w_geo)`` and the free grains' displacements are added to ``N w_geo``;
4. the penetrator (2D: ghost disks on the cone's outline; 3D: the gmsh surface of
   :func:`meshes.penetration.cone_penetrometer` or :func:`~meshes.penetration.flat_pile`
   covered by ghost spheres, :func:`dem.rigid.sample_surface`) moves down at constant
   velocity; per FE step the DEM takes ``substeps`` explicit steps with the band's ghosts
   following the FE displacement (interpolated in time from the last two FE states), the
   free grains' displacements are projected onto the window's FE nodes (eq. 79-90), relaxed,
   and the FE step is solved (generalized-alpha). One Gauss-Seidel pass per FE step (loose
   coupling), with the interface residual reported; ghosts moving beyond twice the
   penetrator's travel stop the run with :class:`CouplingUnstable`.

Outputs: tip resistance ``q_c`` (vertical force on the cone / pile base over the tip area:
cone width per unit thickness in 2D, ``pi R^2`` in 3D), sleeve friction ``f_s`` (vertical
force on a friction sleeve of 3.75 cone diameters just above the cone over its fixed area,
ISO 22476-1) and the friction ratio against depth (:func:`~coupling.apps.penetration.
penetrators.cone_record`). :meth:`CoupledPenetration.
save_checkpoint` writes everything :meth:`~CoupledPenetration.run` needs to continue exactly.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path
from types import SimpleNamespace

import dolfinx_solver  # noqa: F401

import numpy as np

from coupling.apps.penetration.chamber import (
    apply_loads,
    box_around,
    box_width,
    consolidate,
    consolidate_window,
    plate_servo,
    side_servos,
    smooth_walls,
    surcharge,
    top_plate,
)
from coupling.apps.penetration.parameters import VERTICAL, PenetrationParameters
from coupling.apps.penetration.penetrators import cone_clump, cone_parts, cone_record, penetrator_clump, tip_height
from coupling.calibration import lattice_estimate, voigt_estimate
from coupling.interface import IQNILS, CouplingInterface, IQNOptions
from coupling.reactions import GhostReactions, window_weight
from coupling.regions import Box, CouplingRegions
from coupling.substep import GhostMotion, sub_cycle
from dem import GHOST, ContactMaterial, Particles, Simulation
from dem.bonded import hexagonal_lattice
from dem.timestep import DEFAULT_SAFETY, rayleigh_dt
from granfe.dynamics import GeneralizedAlpha
from granfe.explicit import CentralDifference
from granfe.materials import MicropolarMaterial
from granfe.models.micropolar import Micropolar
from granfe.problem import ContinuumProblem

__all__ = ["PenetrationParameters", "CoupledPenetration", "DemPenetration", "cone_record",
           "CouplingUnstable", "cone_clump", "penetrator_clump", "tip_height", "cone_parts"]

#: the continuum's generalised-alpha spectral radius at infinite frequency
RHO_INF = 0.8


class CouplingUnstable(RuntimeError):
    """The DE x FE exchange diverged (ghost motion beyond its bound, or NaN)."""


def contact_material(prm: PenetrationParameters) -> ContactMaterial:
    """The grains' contact law: linear disks of unit thickness in 2D (a line contact has no
    Hertz radius law that the sphere formulas would give; E then only enters the time-step
    estimate), Hertz-Mindlin spheres in 3D."""
    if prm.dim == 2:
        return ContactMaterial(E=prm.kn, nu=prm.nu, density=prm.density, friction=prm.friction,
                               restitution=prm.restitution, law="linear", kn=prm.kn,
                               kt=prm.kt_over_kn * prm.kn)
    return ContactMaterial(E=prm.youngs_modulus, nu=prm.nu, density=prm.density,
                           friction=prm.friction, restitution=prm.restitution, law="hertz_mindlin")


def dem_time_step(prm: PenetrationParameters, grain_radius: np.ndarray) -> float | None:
    """3D: 0.2 of the grains' Rayleigh step (the clump's smaller spheres are ghosts: their
    own stability does not matter); 2D: None (the engine's default of the linear law)."""
    if prm.dim == 2:
        return None
    return DEFAULT_SAFETY["hertz_mindlin"] * rayleigh_dt(grain_radius, prm.youngs_modulus,
                                                         prm.nu, prm.density)


def check_push(prm: PenetrationParameters, dt: float) -> None:
    """The penetrator must move a small fraction of a grain radius per DEM step, or contacts
    are crossed in a step or two and the forces are garbage, not an instability."""
    per_step = prm.velocity * dt
    if per_step > 0.05 * prm.radius:
        raise ValueError(f"velocity = {prm.velocity} m/s moves the penetrator {per_step:.3g} m per "
                         f"DEM step (dt = {dt:.3g} s), more than 0.05 grain radius "
                         f"({0.05 * prm.radius:.3g} m): impacts at that speed overlap grains by "
                         f"a sizeable part of their radius; lower the velocity (or dt_factor) to at "
                         f"most {0.05 * prm.radius / dt:.3g} m/s")


def lower_penetrator(p, n: int, pen0: np.ndarray, r_pen: float, prm) -> None:
    """A packing settles by a few grain radii (more in a deep full chamber than in a window):
    move the penetrator clump ``pen0`` (in place, and its particles after the ``n`` grains)
    down so that its lowest point is 0.1 grain radius above the settled grains it can meet,
    the same start for every packing instead of a push through air."""
    ax = VERTICAL[prm.dim]
    lateral = [k for k in range(prm.dim) if k != ax]
    near = np.linalg.norm(p.x[:n][:, lateral], axis=1) < prm.cone_radius + 2 * prm.radius
    if not near.any():
        return
    top = float((p.x[:n, ax][near] + p.radius[:n][near]).max())
    shift = top + 0.1 * prm.radius - float((pen0[:, ax] - r_pen).min())
    if shift < 0:
        pen0[:, ax] += shift
        p.x[n:n + len(pen0)] = pen0


def _cone_and_material(prm, top):
    """The penetrator clump above ``top`` (centres, radius, tip mask) and the contact law."""
    shaft = prm.depth + 3 * prm.cone_radius
    if prm.dim == 2:
        pen, r_pen, on_cone = cone_clump(prm.cone_radius, prm.apex_deg, shaft, prm.radius)
        # the clump's envelope r_pen + 0.1 grain radius above the grains' tops
        pen[:, 1] += float(top + 1.1 * prm.radius + r_pen - (pen[:, 1].min() - r_pen))
    else:
        pen, r_pen, on_cone = penetrator_clump(prm, shaft)
        # the clump's envelope (its lowest sphere's bottom) 0.1 grain radius above the grains
        pen[:, 2] += float(top + 1.1 * prm.radius - (pen[:, 2].min() - r_pen))
    return pen, r_pen, on_cone, contact_material(prm)


def grain_lattice(prm, lo, hi, rng):
    """Centres (n, 3) on a lattice filling [lo, hi] (hexagonal in 2D; fcc in 3D, the centres
    jittered within a gap of 2 % of a diameter) and radii reduced by up to ``jitter``."""
    if prm.dim == 2:
        x = hexagonal_lattice(lo, hi, prm.radius)
    else:
        from dem.packing import lattice_packing

        x, _ = lattice_packing(lo, hi, prm.radius, kind="fcc", gap=0.02, jitter=1.0, seed=prm.seed)
    return x, prm.radius * (1 - prm.jitter * rng.random(len(x)))


def _settle(sim, prm, n: int, free_rows, width: float, log, plate: int | None = None,
            height: float | None = None) -> list:
    """Settle the grains before the push: under gravity for ``prm.settle_time`` (a free
    surface), or consolidated under the chamber's vertical stress on the top row of
    ``free_rows`` (among the first ``n`` rows, the grains) spanning ``width`` [m], or under
    the top plate (wall ``plate``, 3D) (:mod:`coupling.apps.penetration.chamber`; a
    `dem.DistributedSimulation` is given the specimen's ``height`` [m]). Returns the servos
    to keep acting in the push (the plate's)."""
    if prm.vertical_stress == 0:
        sim.step(int(np.ceil(prm.settle_time / sim.dt)))
        return []
    if plate is not None:
        servo = plate_servo(prm, plate, width ** (prm.dim - 1))
        consolidate(sim, prm, log, controllers=[servo], height=height,
                    grains=None if height is None else n)
        return [servo]
    apply_loads(sim, surcharge(sim.p.x[:n], free_rows, prm, width))
    consolidate(sim, prm, log)
    return []


def _gravity(prm):
    g = np.zeros(3)
    g[VERTICAL[prm.dim]] = -prm.gravity
    return g


# ---- the DEM part of a checkpoint -------------------------------------------------------------
def _dem_state(sim: Simulation) -> dict:
    """``sim.state_dict()`` under ``dem.`` keys, plus the positions ``p.x`` (the restart's
    particle-count check reads them)."""
    return {f"dem.{k}": np.asarray(v) for k, v in sim.state_dict().items()} | {"p.x": sim.p.x.copy()}


def _check_particle_count(sim: Simulation, data) -> None:
    if len(data["p.x"]) != sim.p.n:
        raise ValueError(f"checkpoint holds {len(data['p.x'])} particles, the simulation {sim.p.n}")


def _load_dem_state(sim: Simulation, data) -> None:
    """Inverse of :func:`_dem_state` on a simulation built with the same particle count."""
    _check_particle_count(sim, data)
    sim.load_state({k[4:]: v for k, v in data.items() if k.startswith("dem.")})


def _skin(prm) -> float:
    """The grains' neighbour-list skin [m]: one grain radius (Simulation's default is a fifth:
    the cone's spheres move half of that in ~10 DEM steps, so the lists rebuilt once an FE step
    at 14-15 ms a build, 10k-grain window). Measured on the 3D chamber's 2 cm window, pushed,
    200 DEM steps from one state: 4.45 ms a DEM step with the default skin, 3.54 / 3.47 / 3.27
    ms with 2 / 3 / 5 times it (5 times lists 1.5x the pairs, an open one ~3 ns to test)."""
    return prm.radius


def _distributed_run(p, materials, walls, prm, radius, comm):
    """The full DEM's `dem.DistributedSimulation` over the ranks of ``comm`` (``p`` on every
    rank; rank 0's is scattered): the serial run's step, set through the constructor.

    Its halo skin is two grain radii (the default is 0.8): the cone's spheres are owned
    particles, and the ranks decompose again each time the cone moves half the halo skin; a
    wider halo only adds copies out of contact reach (their exchange, no pairs). Measured on
    4624 spheres and a 12 mm push on 2 ranks: 9 decompositions in the push instead of 23,
    the push 15 % faster, the same q_c."""
    from dem.parallel import DistributedSimulation

    # as the serial run, dt_factor scales the step after its check (force_dt)
    return DistributedSimulation(p if comm.rank == 0 else None, materials, walls, _gravity(prm),
                                 dt=dem_time_step(prm, radius) * prm.dt_factor, comm=comm,
                                 force_dt=True, allow_overlap=True, skin=_skin(prm), halo_skin=2 * prm.radius)


class DemPenetration:
    """The same penetration fully as DEM: grains fill the whole chamber (a box of the
    chamber's width in 3D), held by walls (no continuum objects are built). The reference
    for :class:`CoupledPenetration`.

    ``comm``: a communicator of more than one rank runs the grains as a `dem.
    DistributedSimulation` over its ranks (the 3D chamber; every rank
    constructs and runs the model, rank 0 alone logs): the plate's servo reads the plate's
    force summed over the ranks, the cone's spheres move by global id and their forces come
    from their owners, so every rank holds the same history, equal to the serial one to
    round-off at first (the packings are chaotic). None or one rank: a `dem.Simulation`.
    An explicit argument, not the launcher's rank count: a serial model inside an MPI job
    (a test, the coupled runs' own references) stays serial."""

    def __init__(self, prm: PenetrationParameters, log=print, comm=None):
        from dem import PlaneWall

        self.prm = prm
        self.distributed = comm is not None and comm.size > 1
        if self.distributed:
            if prm.dim != 3:  # (2D: its surcharge and BC1 servos read every particle)
                raise ValueError(f"DemPenetration on {comm.size} ranks: the 3D chamber only "
                                 f"(dim = 3), got dim = {prm.dim}")
            if comm.rank != 0:
                def log(message):
                    pass
        rng = np.random.default_rng(prm.seed)
        W, H, dim, ax = prm.chamber_width, prm.chamber_depth, prm.dim, VERTICAL[prm.dim]
        lo = (-W / 2, -H) if dim == 2 else (-W / 2, -W / 2, -H)
        hi = (W / 2, 0.0) if dim == 2 else (W / 2, W / 2, 0.0)
        x, radius = grain_lattice(prm, lo, hi, rng)
        Particles.spheres(x, radius, prm.density, dim=dim).check_overlaps()
        pen, r_pen, self.on_cone, material = _cone_and_material(prm, x[:, ax].max())
        self.pen0, self.parts = pen.copy(), cone_parts(pen, self.on_cone, prm)
        n = len(x)
        p = Particles.spheres(np.vstack([x, pen]), np.concatenate([radius, np.full(len(pen), r_pen)]),
                              prm.density, dim=dim,
                              kind=np.concatenate([np.zeros(n), np.full(len(pen), GHOST)]).astype(np.int8))
        # a chamber under a vertical stress has smooth (lubricated) walls: rough ones would
        # carry the load by friction (a silo)
        wm, materials = (1, smooth_walls(material)) if prm.vertical_stress > 0 else (0, material)
        walls = [PlaneWall(tuple(-W / 2 * e), tuple(e), material=wm) for e in np.eye(3)[:dim - 1]]
        walls += [PlaneWall(tuple(W / 2 * e), tuple(-e), material=wm) for e in np.eye(3)[:dim - 1]]
        walls.append(PlaneWall(tuple(-H * np.eye(3)[ax]), tuple(np.eye(3)[ax]), material=wm))
        plate = None
        if dim == 3 and prm.vertical_stress > 0:
            plate = len(walls)
            walls.append(top_plate(x, radius, dim))
        self.n_grains, self.pen_index = n, np.arange(n, n + len(pen))
        height = None  # the specimen's, for the consolidation (the serial run reads its own)
        if self.distributed:
            self.sim = _distributed_run(p, materials, walls, prm, radius, comm)
            height = float(np.ptp(x[:, ax])) + 2 * prm.radius
        else:
            self.sim = Simulation(p, materials, walls=walls, gravity=_gravity(prm),
                                  dt=dem_time_step(prm, radius), allow_overlap=True, skin=_skin(prm))
            self.sim.dt *= prm.dt_factor
            self.sim.compute_forces(update_history=False)
        self.clump_internal = self.clump_forces()
        t0 = time.perf_counter()
        self.servos = _settle(self.sim, prm, n, np.arange(n), W, log, plate, height)
        # BC1: the side walls servo-controlled at the lateral stress they carry now
        # (the 2D disks' modulus is of the order of kn, N/m per m thickness)
        if prm.lateral == "stress":
            self.servos += side_servos(self.sim, list(range(2 * (dim - 1))), float(np.ptp(self.sim.p.x[:n, ax])),
                                       W, prm.kn, prm.substeps * self.sim.dt, prm.velocity)
        grains = self.sim.p if not self.distributed else SimpleNamespace(
            x=np.vstack([self.sim.values_of(np.arange(n), "x"), self.pen0]), radius=p.radius)
        # (distributed: the clump is where pen0 says from the first prescribed step on)
        lower_penetrator(grains, n, self.pen0, r_pen, prm)
        log(f"full DEM: settled {n} grains in {time.perf_counter() - t0:.1f} s")
        self.history: list[dict] = []

    def clump_forces(self) -> np.ndarray:
        """(k, 3) [N]: the forces on the clump's spheres now, their own contacts included
        (collective when distributed: from the spheres' owners)."""
        if self.distributed:
            return self.sim.values_of(self.pen_index, "force")
        return self.sim.p.force[self.pen_index].copy()

    def run(self, progress=None):
        """Push the cone to ``prm.depth`` in blocks of ``prm.substeps`` DEM steps, the servos
        acting once a block; returns the history of cone records (every rank's, when
        distributed)."""
        prm, sim = self.prm, self.sim
        check_push(prm, sim.dt)
        block = prm.substeps * sim.dt
        n_steps = int(np.ceil(prm.depth / prm.velocity / block))
        depth, t = 0.0, 0.0
        for k in range(n_steps):
            t0 = time.perf_counter()
            for servo in self.servos:   # each wall's speed, held over the block
                servo(sim)
            depth = sub_cycle(sim, prm.substeps, (self.pen_index, self.pen0), depth, prm.velocity,
                              VERTICAL[prm.dim])
            t += block
            f = self.clump_forces() - self.clump_internal
            self.history.append(cone_record(prm, f, self.parts, depth, k + 1, t,
                                            wall_time=time.perf_counter() - t0))
            if progress is not None:
                progress(self.history[-1])
        return self.history


class CoupledPenetration:
    """Builds and runs the coupled penetration (see the module docstring).

    Args:
        prm: the parameters (``prm.dim`` picks 2D or 3D).
        comm: the FE mesh's communicator (the grains are replicated on every rank).
        log: where progress messages go.
        checkpoint: a directory written by :meth:`save_checkpoint` (same parameters, same
            rank count): the settled packing, the continuum constants and the state of the
            run are read from it instead of settling again; :meth:`run` then continues.
    """

    def __init__(self, prm: PenetrationParameters, comm, log=print, checkpoint=None):
        try:
            self._build(prm, comm, log, checkpoint)
        except Exception as err:
            # a set-up failure after the grains exist hands their state to the caller to keep
            sim = getattr(self, "sim", None)
            if sim is not None and hasattr(sim, "p"):
                err.grains = sim.p.state_dict()
            raise

    def _build(self, prm: PenetrationParameters, comm, log, checkpoint):
        from meshes.penetration import build_chamber

        self.prm, self.comm, self.log = prm, comm, log
        dim, ax = prm.dim, VERTICAL[prm.dim]
        rng = np.random.default_rng(prm.seed)
        d = 2 * prm.radius
        band = prm.ghost_width * d
        a, b = prm.window_half_width, prm.window_depth
        if self._refined_depth() + band >= prm.chamber_depth:
            # before the grains settle (the mesh would refuse it after); a full-DEM run of the
            # same parameters never meshes, so the check is the coupled run's
            raise ValueError(f"window_depth = {prm.window_depth} m and its ghost band ({band:.3g} m) reach the "
                             f"chamber's base (chamber_depth = {prm.chamber_depth} m): deepen the chamber or make "
                             "the window shallower")
        # ---- grains: jittered lattice over window + band, then settle with the band held
        lo, hi = [-a - band] * (dim - 1) + [-b - band], [a + band] * (dim - 1) + [0.0]
        lattice, radius = grain_lattice(prm, tuple(lo), tuple(hi), rng)
        self.regions = CouplingRegions(Box(tuple([-a] * (dim - 1) + [-b]), tuple([a] * (dim - 1) + [2 * b])),
                                       ghost_width=band,
                                       handshake=prm.handshake * prm.element_size_window)
        kinds = self.regions.particle_kinds(lattice[:, :dim])
        keep = kinds >= 0
        self.x_grains, self.kinds = lattice[keep], kinds[keep].astype(np.int8)
        radius = radius[keep]
        n = len(self.x_grains)
        pen, r_pen, self.on_cone, self.material = _cone_and_material(prm, self.x_grains[:, ax].max())
        self.pen0, self.parts = pen.copy(), cone_parts(pen, self.on_cone, prm)
        x = np.vstack([self.x_grains, pen])
        r = np.concatenate([radius, np.full(len(pen), r_pen)])
        kind = np.concatenate([np.where(self.kinds == 1, GHOST, 0), np.full(len(pen), GHOST)]).astype(np.int8)
        Particles.spheres(self.x_grains, radius, prm.density, dim=dim).check_overlaps()
        p = Particles.spheres(x, r, prm.density, dim=dim, kind=kind)
        self.n_grains, self.pen_index = n, np.arange(n, n + len(pen))
        # the penetrator's spheres overlap each other by construction (a smooth rigid outline);
        # under a vertical stress the window and its band consolidate together inside smooth
        # walls round the band (chamber.consolidate_window)
        walls, materials, plate = (), self.material, None
        if prm.vertical_stress > 0:
            walls, materials = box_around(self.x_grains, radius, dim), smooth_walls(self.material)
            if dim == 3:
                plate = len(walls)
                walls.append(top_plate(self.x_grains, radius, dim))
        # the force-carrying exchange reads a ghost's force as the free grains' push on it
        self.forces = prm.interface == "forces"
        self.distributed = False   # the push's grains split over the ranks (end of the set-up)
        self.sim = Simulation(p, materials, walls=walls, gravity=_gravity(prm),
                              dt=dem_time_step(prm, radius), allow_overlap=True, skin=_skin(prm),
                              prescribed_pairs=not self.forces)
        self.sim.dt *= prm.dt_factor
        # the clump's own (constant) internal forces, to subtract from the penetrator's resultant
        self.sim.compute_forces(update_history=False)
        self.clump_internal = self.sim.p.force[self.pen_index].copy()
        self.history: list[dict] = []
        # wall time split of each FE step of run() (not part of the history or checkpoints)
        self.step_timings: list[dict] = []
        self.depth = 0.0
        self.servos = []   # the top plate's (3D chamber), once per FE step
        saved = None
        if checkpoint is None:
            t0 = time.perf_counter()
            if prm.vertical_stress > 0:
                servo = consolidate_window(self.sim, prm, n, np.flatnonzero(self.kinds == 1),
                                           box_width(self.x_grains, radius, dim), log, plate=plate)
                self.servos = [] if servo is None else [servo]
            else:
                _settle(self.sim, prm, n, np.flatnonzero(self.kinds == 0), 2 * (a + band), log)
            e = self.sim.energy()
            log(f"settled {n} grains in {time.perf_counter() - t0:.1f} s "
                f"({self.sim.nsteps} steps of {self.sim.dt:.3g} s), kinetic energy "
                f"{e['kinetic_translational']:.3g} J")
            lower_penetrator(self.sim.p, n, self.pen0, r_pen, prm)
            self.x_ref = self.sim.p.x[:n].copy()
            self.material_fe, self.contact_stats = self._continuum_material()
            if prm.continuum_stiffness != 1.0:
                c = prm.continuum_stiffness
                m = self.material_fe
                self.material_fe = replace(m, lam=c * m.lam, mu=c * m.mu, kappa=c * m.kappa,
                                           alpha=c * m.alpha, beta=c * m.beta, gamma=c * m.gamma)
            # the continuum reaches the highest settled grain centre (every grain inside the mesh)
            self.surface = float(self.x_ref[:, ax].max() + 1e-3 * prm.radius)
        else:
            if prm.vertical_stress > 0 and plate is None:
                apply_loads(self.sim, surcharge(self.sim.p.x[:n], np.flatnonzero(self.kinds == 0), prm,
                                                box_width(self.x_grains, radius, dim)))
            saved = self._read_checkpoint(Path(checkpoint))
            if plate is not None:
                self.servos = [plate_servo(prm, plate, saved["state"]["plate_area"])]
        # ---- continuum: chamber, stiffness from the settled contacts
        if dim == 2:
            data = build_chamber(comm, 2, width=prm.chamber_width, depth=prm.chamber_depth,
                                 window_width=2 * (a + band), window_depth=self._refined_depth() + band,
                                 h_window=prm.element_size_window, h_far=prm.element_size_far)
        elif prm.vertical_stress > 0:
            # the chamber under a vertical stress: the full DEM's box of plane walls
            data = build_chamber(comm, 3, shape="box", width=prm.chamber_width, depth=prm.chamber_depth,
                                 window_width=2 * (a + band), window_depth=self._refined_depth() + band,
                                 h_window=prm.element_size_window, h_far=prm.element_size_far)
        else:
            data = build_chamber(comm, 3, radius=prm.chamber_width / 2, depth=prm.chamber_depth,
                                 window_radius=np.sqrt(2) * (a + band), window_depth=self._refined_depth() + band,
                                 h_window=prm.element_size_window, h_far=prm.element_size_far)
        data.mesh.geometry.x[:, ax] += self.surface
        names = {k: tag for k, (gd, tag) in data.physical_groups.items() if gd == dim - 1}
        # "redundant": the same bits run to run on the same rank count (granfe.solvers.REDUNDANT)
        model = self._continuum_model()
        options = {}
        if not model.linear:
            # Newton on the closed-form return can cycle at the residual's round-off floor of
            # the elastic-plastic switches: stop at a millionth of the nodal forces the
            # initial stress puts on a window element (the forces the grains exchange)
            scale = self._stress_scale() * prm.element_size_window ** (dim - 1)
            options = {"snes_atol": 1e-6 * scale}
        self.problem = ContinuumProblem(data.mesh, model, facet_tags=data.facet_tags, tag_names=names,
                                        degree=(1,) * len(model.fields(dim)), prefix="cpt_", solver="redundant",
                                        petsc_options=options)
        self.problem.fix("bottom", "u")
        self.problem.fix("bottom", "phi")
        if dim == 2 or prm.vertical_stress > 0:
            # the increment from the consolidated state: a constant vertical stress on top
            # (traction-free), the sides on rollers (BC3) or traction-free (BC1)
            if prm.lateral == "rigid":
                for side, component in (("left", "u_x"), ("right", "u_x"), ("front", "u_y"), ("back", "u_y")):
                    if side in names:
                        self.problem.fix(side, component)
        else:
            self._geostatic_loads()
            self.problem.solve()   # the geostatic state w_geo, before any dof is prescribed
        if self.forces:
            # the grains carry the material inside the window: the continuum's is weighted out
            window = self.regions.window
            self.problem.set_weight(window_weight(self.problem.domain,
                                                  lambda x: window.signed_distance(x[:, :dim]) < 0))
            self.interface = GhostReactions(self.problem, self.x_ref, self.kinds)
        else:
            self.interface = self._displacement_interface()
        self.free_local = np.flatnonzero(self.kinds == 0)
        self.ghost_local = np.flatnonzero(self.kinds == 1)
        self._g_ref, self._q_ref = None, None
        if dim == 3 and prm.vertical_stress == 0:
            self._hold_geostatic_state()
        # a micromorphic phi is prescribed as this (the geostatic state's) plus the grains' fit
        self._phi_ref = self.interface.prescribed_values()[self.interface.fields[0].prescribed.size:] \
            if getattr(self.interface, "micro", None) is not None else None
        self.dt_fe = prm.substeps * self.sim.dt
        self._continuum_loads()   # (before the stepper compiles its forms)
        self.stepper = (CentralDifference(self.problem, self.dt_fe, damping=prm.continuum_damping)
                        if prm.continuum_integrator == "explicit"
                        else GeneralizedAlpha(self.problem, self.dt_fe, rho_inf=RHO_INF))
        self.g_prev = self._ghost_motion()
        # the iterated exchange's accelerator (unused by the loose one); the last step's pairs
        # are reused: the next step's map is nearly the same
        self.accelerator = self._accelerator()
        # the forces exchange: the free grains' push on the ghosts at the start (the FE holds the
        # increment from there), and the last one the continuum was loaded with (relaxed)
        self.f0 = self.f_applied = None
        if self.forces and saved is None:   # (a restart reads them: no force pass on its state)
            self.sim.compute_forces(update_history=False)
            self.f0 = self.sim.p.force[self.ghost_local, :dim].copy()
            self.f_applied = np.zeros_like(self.f0)
        # the push's grains over the ranks: the consolidated window continued as a distributed run
        self._distribute_grains(saved)
        if saved is not None:
            self._restore_run(saved)
        self._g_now = None   # ghost motion of the current FE state, kept by each step for the next

    def _distribute_grains(self, saved):
        """``self.sim`` becomes a `dem.DistributedSimulation` continuing the serial one (every
        rank's is the same): split by space, halo skin two grain radii (as the full DEM's:
        the cone's spheres are owned particles); a restart then reads each rank's part."""
        from dem.parallel import DistributedSimulation, RecursiveBisection

        self.distributed = self.prm.distribute_grains and self.comm.size > 1
        if not self.distributed:
            return
        serial = self.sim
        self.particles = serial.p   # radii, masses, kinds: fixed for the run
        # cuts through the consolidated window across gravity, kept by checkpoints: a restart
        # decomposes where the run did (the same pair orders, the same bits)
        if saved is None:
            axes = [a for a in range(3) if a != VERTICAL[self.prm.dim]]
            self.owner = RecursiveBisection.from_points(serial.p.x, self.comm.size, axes)
        else:
            g = saved["grains"]
            self.owner = RecursiveBisection(g["owner.axis"], g["owner.cut"], g["owner.below"],
                                            g["owner.above"], self.comm.size)
        self.sim = DistributedSimulation.from_simulation(serial, self.comm, owner=self.owner,
                                                         halo_skin=2 * self.prm.radius,
                                                         prescribed_pairs=not self.forces)
        if saved is not None:
            self.sim.load_state(saved["grains_rank"])

    # ---- set-up -------------------------------------------------------------------------
    def _continuum_model(self):
        """The continuum model of ``prm.continuum`` with the settled packing's constants; the
        Drucker-Prager one starts from the window's consolidated mean stress."""
        prm = self.prm
        if prm.continuum == "micropolar":
            return Micropolar(self.material_fe)
        if prm.continuum == "micromorphic":
            from granfe.models.micromorphic import Micromorphic

            return Micromorphic(self._micromorphic_material())
        if prm.continuum == "micromorphic_drucker_prager":
            return self._micromorphic_drucker_prager()
        from granfe.models.drucker_prager import DruckerPragerMaterial, MicropolarDruckerPrager

        elastic = replace(self.material_fe, alpha=0.0, beta=0.0)
        s0 = self._initial_stress()
        phi, psi = self._cone_angles()
        # 2D: the disks' out-of-plane stress is unknown, taken as the lateral one
        mat = DruckerPragerMaterial(elastic, prm.continuum_cohesion, phi, psi,
                                    hardening=prm.continuum_hardening,
                                    match="plane_strain" if prm.dim == 2 else "triaxial_compression",
                                    initial_stress=(s0[0], s0[1], s0[0]) if prm.dim == 2 else s0)
        return MicropolarDruckerPrager(mat)

    def _cone_angles(self) -> tuple[float, float]:
        """(friction, dilatancy) [deg] of the continuum's cone: the scene's, or the element
        tests' peak friction and dilatancy (``continuum_constants = "calibrated"``)."""
        prm = self.prm
        phi, psi = prm.continuum_friction_deg, prm.continuum_dilatancy_deg
        cal = self.contact_stats.get("calibration")
        if cal is not None:
            phi = cal["friction_peak_deg"]
            psi = min(max(cal["dilatancy_deg"], 0.0), phi)
        return phi, psi

    def _micromorphic_drucker_prager(self):
        """The micromorphic solid of :meth:`_micromorphic_material` with the scene's cone on
        its macro stress S (the total stress of a homogeneous state, where the relative
        stress vanishes: the micropolar Drucker-Prager model's cone on sym sigma), matched to
        Mohr-Coulomb on the compression meridian; the micro and higher-order levels elastic.
        Its moduli couple the levels (D = sigma = -b), so the levels return together at the
        points (:class:`~granfe.models.micromorphic_iterative.MicromorphicDruckerPragerIterative`;
        the closed-form model needs D = 0)."""
        from granfe.models.micromorphic_drucker_prager import Cone, MicromorphicDruckerPragerMaterial
        from granfe.models.micromorphic_iterative import MicromorphicDruckerPragerIterative

        prm = self.prm
        phi, psi = self._cone_angles()
        cone = Cone(prm.continuum_cohesion, phi, psi, hardening=prm.continuum_hardening,
                    match="triaxial_compression")
        self._check_geostatic_cone(cone)
        return MicromorphicDruckerPragerIterative(
            MicromorphicDruckerPragerMaterial(self._micromorphic_material(), macro=cone))

    def _check_geostatic_cone(self, cone) -> None:
        """Refuse a cone the geostatic state (:meth:`_geostatic_loads`: sigma_h = K0 sigma_v,
        K0 the packing's elastic one) leaves at the chamber's base: without cohesion K0 must
        reach about Ka = (1 - sin phi) / (1 + sin phi), and the affine estimate's K0 of a
        settled packing is far below (0.03 measured): every point would yield under its own
        weight, against side tractions that cannot hold it (a collapse, solved for minutes)."""
        from granfe.models.micromorphic_drucker_prager import Cone

        prm, m = self.prm, self.material_fe
        k0, sigma_v = self._geostatic_k0(), m.rho * prm.gravity * prm.chamber_depth
        A, _, strength = cone.constants
        # f = sqrt(J2) + A p - k at the base (compression: p = -(1 + 2 K0) sigma_v / 3)
        load = sigma_v * (abs(1 - k0) / np.sqrt(3) - A * (1 + 2 * k0) / 3)
        if load > strength:
            per_pa = Cone(1.0, cone.friction_deg, cone.dilatancy_deg).constants[2]
            raise ValueError(
                f"continuum = 'micromorphic_drucker_prager': the geostatic stress lies outside its cone at "
                f"the chamber's base (sigma_v = {sigma_v:.4g} Pa at chamber_depth = {prm.chamber_depth} m, "
                f"sigma_h = K0 sigma_v with the packing's elastic K0 = {k0:.3g}; friction "
                f"{cone.friction_deg:.3g} deg): the continuum would collapse under its own weight. "
                f"continuum_cohesion must be >= {load / per_pa:.4g} Pa (got {cone.cohesion:.4g})")

    def _micromorphic_material(self):
        """The packing's micropolar constants (lam, mu, kappa, gamma; alpha = beta = 0) as a
        micromorphic solid (Eringen's relative deformation ``g = grad u - phi``, ``G = mu +
        kappa / 2``, ``b = prm.continuum_micro_stiffness G``)::

            W = lam/2 tr(eps)^2 + G |eps|^2 + b/2 |sym g|^2 + kappa/2 |skew g|^2 + gamma/4 |grad phi|^2

        In the 18 moduli (``eps:A:eps/2 + E:B:E/2 + G:C:G/2 + eps:D:E``, ``E = 2 eps - g``):
        mu' = G + 2 b, sigma = -b, kappa' = (kappa - b) / 2, nu = -(kappa + b) / 2, eta = tau = 0,
        tau7 = gamma / 2 and the other taus 0; Smith's conditions hold for b, kappa, gamma > 0
        and 3 lam + 2 G > 0. Its homogeneous states have g = 0 (phi = grad u, micro follows
        macro, the grains' fit), so lam and G are the grains' and the geostatic K0 the
        micropolar one's; a skew phi (a rotation) has the micropolar energy, and b -> inf is
        the micropolar solid. Micro-inertia j / 2 (the micropolar rotary inertia j)."""
        from granfe.models.micromorphic import MicromorphicMaterial

        m = self.material_fe
        g = m.mu + m.kappa / 2
        b = self.prm.continuum_micro_stiffness * g
        zero = dict.fromkeys(("tau1", "tau2", "tau3", "tau4", "tau5", "tau6", "tau8", "tau9", "tau10",
                              "tau11"), 0.0)
        return MicromorphicMaterial(lam=m.lam, mu=g + 2 * b, eta=0.0, tau=0.0, kappa=(m.kappa - b) / 2,
                                    nu=-(m.kappa + b) / 2, sigma=-b, tau7=m.gamma / 2, **zero,
                                    rho=m.rho, micro_inertia=m.j / 2)

    def _stress_scale(self) -> float:
        """[Pa] the stress the grains exchange with the continuum: the largest component of
        the consolidated window's initial stress, or on a 3D free surface the geostatic
        vertical stress at the window's base (the continuum's own, no initial stress)."""
        prm = self.prm
        if prm.dim == 3 and prm.vertical_stress == 0:
            return self.material_fe.rho * prm.gravity * prm.window_depth
        return max(abs(v) for v in self._initial_stress())

    def _initial_stress(self) -> tuple[float, ...]:
        """The consolidated window's mean stress, measured once (or read from a checkpoint)."""
        if getattr(self, "initial_stress", None) is None:
            self.initial_stress = self._window_stress()
        return self.initial_stress

    def _window_stress(self) -> tuple[float, ...]:
        """The diagonal (sigma_xx, sigma_yy[, sigma_zz]) [Pa, tension positive] of the free
        grains' mean (Love-Weber) stress, over the contacts between free grains at least two
        diameters below the surface and inside the window (in 2D the out-of-plane stress of
        disks is unknown: the Drucker-Prager start takes sigma_zz = sigma_xx)."""
        prm, sim, n = self.prm, self.sim, self.n_grains
        dim, ax = prm.dim, VERTICAL[prm.dim]
        pairs, f, b = sim.contact_forces(return_branch=True)
        i, j = pairs[:, 0], pairs[:, 1]
        x, d = sim.p.x, 2 * prm.radius
        top = float(x[:n, ax].max())
        inner = np.zeros(sim.p.n, bool)
        inner[:n] = self._inner_grains(x[:n])
        if (inner[i] & inner[j]).sum() < 20:
            raise ValueError("the window holds fewer than 20 contacts between free grains away from "
                             "its edges: too small to take the continuum's initial stress from")
        # a contact with one end inside counts half (Love-Weber over the inner region)
        weight = 0.5 * (inner[i].astype(float) + inner[j])
        sigma = np.einsum("k,ka,kb->ab", weight, f, b)
        # the window's base is where its lattice was built (the ghosts below it held), its top
        # where the grains settled: a consolidated 3D window stands 16 mm lower, and the
        # height window_depth - 3 d put its vertical stress at 85 kPa for 104
        volume = (2 * (prm.window_half_width - d)) ** (dim - 1) * (top + prm.window_depth - 3 * d)
        return tuple(float(sigma[k, k] / volume) for k in range(dim))

    def _inner_grains(self, x: np.ndarray) -> np.ndarray:
        """(n,) mask of the free grains at ``x`` (n, 3) at least a diameter inside the window's
        sides and base and two below its top: the region its stress and strain are read over."""
        prm, dim, ax, d = self.prm, self.prm.dim, VERTICAL[self.prm.dim], 2 * self.prm.radius
        top = float(x[:, ax].max())
        return ((self.kinds == 0) & (np.abs(x[:, :dim - 1]).max(axis=1) < prm.window_half_width - d)
                & (x[:, ax] < top - 2 * d) & (x[:, ax] > -prm.window_depth + d))

    def _continuum_material(self):
        """Micropolar constants and density of the settled packing (module docstring, 3.)."""
        if self.prm.dim == 3:
            return self._continuum_material_3d()
        sim, prm = self.sim, self.prm
        i, j = sim.contacts()
        grains = (i < self.n_grains) & (j < self.n_grains)
        z = 2 * int(grains.sum()) / max(self.n_grains, 1)
        c = lattice_estimate({"coordination": z, "kn": prm.kn, "kt": prm.kt_over_kn * prm.kn}, prm.radius)
        c.pop("name")
        r = sim.p.radius[: self.n_grains]
        lo, hi = self.x_ref[:, :2].min(0), self.x_ref[:, :2].max(0)
        rho = prm.density * np.pi * np.sum(r**2) / np.prod(hi - lo)
        stats = {"contacts": int(grains.sum()), "coordination": z, "density": rho}
        if prm.continuum_constants == "calibrated":
            c, stats["calibration"] = self._calibrated_constants()
        mat = MicropolarMaterial(**c, rho=rho, j=prm.radius**2 / 2)
        return mat, stats

    def _calibrated_constants(self) -> tuple[dict, dict]:
        """Micropolar constants (lam, mu, kappa, gamma) of element tests on a periodic cell of
        the scene's grains (:func:`coupling.calibration.calibrate`: the scenes' jittered
        lattice, compressed to the window's consolidated mean stress), and the record of the
        calibration (with its peak friction and dilatancy angles when the continuum is
        plastic). The lattice estimate overrates the shear modulus of a packing whose
        contacts slide and open (about 1.4x at 75 kPa in the 2D chamber): the calibration measures it."""
        from coupling.calibration import CellTest, calibrate

        prm = self.prm
        p = -float(np.mean(self._initial_stress()))
        if not p > 0:
            raise ValueError(f"continuum.constants = 'calibrated': the window's mean stress {p:.3g} Pa "
                             "is not compressive, nothing to calibrate at")
        plastic = prm.continuum != "micropolar"
        t0 = time.perf_counter()
        # one rank calibrates (the grains are the same on every rank), every rank takes its result
        cal = None
        if self.comm.rank == 0:
            cal = calibrate(CellTest(self.material, prm.radius, dim=prm.dim, pressure=p, packing="lattice",
                                     spread=prm.jitter, seed=prm.seed,
                                     shear_strain=0.3 if plastic else 0.0))
        cal = self.comm.bcast(cal, root=0)
        record = {"pressure": p, "grains": cal.grains, "solid_fraction": cal.solid_fraction,
                  "coordination": cal.coordination, "bulk_modulus": cal.bulk_modulus,
                  "shear_modulus": cal.shear_modulus, "friction_peak_deg": cal.friction_peak_deg,
                  "friction_critical_deg": cal.friction_critical_deg, "dilatancy_deg": cal.dilatancy_deg,
                  "lattice_estimate": cal.estimate, "seconds": time.perf_counter() - t0}
        self.log(f"calibrated the continuum on {cal.grains} grains at p = {p:.4g} Pa in "
                 f"{record['seconds']:.1f} s: K {cal.bulk_modulus:.4g} Pa, G {cal.shear_modulus:.4g} Pa"
                 + (f", peak friction {cal.friction_peak_deg:.1f} deg, dilatancy "
                    f"{cal.dilatancy_deg:.1f} deg" if plastic else ""))
        return {"lam": cal.lam, "mu": cal.mu, "kappa": cal.kappa, "gamma": cal.gamma}, record

    def _continuum_material_3d(self):
        from dem.contact import P_ESTAR, P_GSTAR, pair_table

        sim, prm, n = self.sim, self.prm, self.n_grains
        i, j = sim.contacts()
        grains = (i < n) & (j < n)
        i, j = i[grains], j[grains]
        if len(i) == 0:
            raise ValueError(f"settle_time = {prm.settle_time} s leaves a coordination number of 0 "
                             "(no grain contacts): not a load-bearing packing to take the "
                             "continuum's constants from; settle longer")
        x, r = self.x_ref, sim.p.radius[:n]
        delta = r[i] + r[j] - np.linalg.norm(x[j] - x[i], axis=1)
        a = np.sqrt(r[i] * r[j] / (r[i] + r[j]) * delta)
        row = pair_table([self.material])[0, 0]
        kn, kt = float(np.mean(2 * row[P_ESTAR] * a)), float(np.mean(8 * row[P_GSTAR] * a))
        # coordination and solid fraction away from the ghost band and the free surface
        # (both lack neighbours); the whole packing when the window is too small for that
        d, w, depth = 2 * prm.radius, prm.window_half_width, prm.window_depth
        top = float(x[:, 2].max())
        inner = (np.abs(x[:, :2]).max(axis=1) <= w - d) & (x[:, 2] >= -depth + d) & (x[:, 2] <= top - 2 * d)
        volume = (2 * (w - d)) ** 2 * (top - 2 * d - (-depth + d))
        if inner.sum() < 20:
            inner = np.ones(n, bool)
            volume = np.prod(x.max(0) - x.min(0) + d)
        z = float(np.mean((np.bincount(i, minlength=n) + np.bincount(j, minlength=n))[inner]))
        if not z >= 2:
            raise ValueError(f"settle_time = {prm.settle_time} s leaves a coordination number of "
                             f"{z:.2f} inside the window: not a load-bearing packing to take the "
                             "continuum's constants from; settle longer")
        phi = float(np.sum(4 / 3 * np.pi * r[inner] ** 3) / volume)
        stats = {"contacts": int(len(i)), "coordination": z, "density": prm.density * phi,
                 "solid_fraction": phi, "kn": kn, "kt": kt}
        c = voigt_estimate(stats, float(np.mean(r)))
        c.pop("name")
        if prm.continuum_constants in ("window", "window_isotropic"):
            measured = self._window_modulus()
            shear = 2 * c["mu"] + c["kappa"]
            if prm.continuum_constants == "window":
                # the affine estimate scaled to the window's own constrained modulus (the same
                # Poisson ratio and length): the continuum as stiff as the grains it replaces
                scale = measured["modulus"] / (c["lam"] + shear)
                c = {k: scale * v for k, v in c.items()}
            else:
                # both isotropic constants from the probe: lam mostly from the lateral stress
                # it raised, 2 mu + kappa = 2 G from the rest of its response (the affine
                # estimate's Poisson ratio, ~0.04, is not the grains': their lateral stress
                # follows the vertical one at ~K0); mu : kappa and the length stay affine
                scale = 2 * measured["shear_modulus"] / shear
                c = {k: scale * v for k, v in c.items()} | {"lam": measured["lam"]}
            stats["window_modulus"] = measured | {"voigt_scale": scale}
            self.log(f"window's constrained modulus {measured['modulus'] / 1e6:.4g} MPa in situ, lateral "
                     f"ratio {measured['lateral_ratio']:.3g}: shear {scale:.3g} of the affine estimate")
        if prm.continuum_constants == "calibrated":
            c, stats["calibration"] = self._calibrated_constants()
        return MicropolarMaterial(**c, rho=prm.density * phi, j=0.4 * prm.radius**2), stats

    def _window_modulus(self, increment: float = 0.1) -> dict:
        """The consolidated window's response in situ to the top plate's stress raised by
        ``increment`` of the vertical stress, the grains relaxed (the band held: no lateral
        strain at its edge): the inner region's Love-Weber stress change and its strain (the
        least-squares affine fit of the grains' displacement there), the constrained modulus
        (vertical stress over vertical strain) and lam, G of the isotropic law fitted to both;
        the grains and the plate are put back as they were. Loading, not unloading: the far
        field is pushed by the cone."""
        from dataclasses import replace as with_target

        from dem.control import mean_force_ratio

        prm, sim, n = self.prm, self.sim, self.n_grains
        t0 = time.perf_counter()
        saved, servo = sim.state_dict(), self.servos[0]
        s0, x0 = self._window_stress(), sim.p.x[:n].copy()
        probe = with_target(servo, target=servo.target + increment * prm.vertical_stress)

        def balanced(s):
            # in equilibrium (the grains' ratio) with the plate at its new stress (to 2 % of the
            # increment): the grains start in equilibrium, the plate's stress does not
            error = abs(probe.stress(s) - probe.target) / (0.02 * increment * prm.vertical_stress)
            return max(mean_force_ratio(s), prm.consolidation_tol * error)

        consolidate(sim, prm, lambda m: None, controllers=[probe], ratio=balanced)
        s1, du = np.array(self._window_stress()), sim.p.x[:n] - x0
        inner = self._inner_grains(x0)
        # the inner region's strain: the least-squares affine fit of the grains' displacement
        fit = np.linalg.lstsq(np.c_[np.ones(inner.sum()), x0[inner]], du[inner], rcond=None)[0]
        eps = 0.5 * (fit[1:] + fit[1:].T)
        sim.load_state(saved)
        strain, ds = float(eps[2, 2]), s1 - np.array(s0)
        if not strain < 0:
            raise ValueError(f"the window did not compress under the probe (vertical strain {strain:.3g}): "
                             "no constrained modulus to take the continuum's stiffness from")
        # isotropic ds_ii = lam tr(eps) + 2 G eps_ii (i = x, y, z), least squares in lam and G:
        # with the band held the lateral strains are small and lam ~ ds_h / eps_zz
        d = np.diag(eps)
        (lam, g), *_ = np.linalg.lstsq(np.c_[np.full(3, d.sum()), 2 * d], ds, rcond=None)
        return {"modulus": float(ds[2] / strain), "stress_change": float(ds[2]), "strain": strain,
                "lateral_stress_change": float(ds[:2].mean()), "lateral_strain": float(d[:2].mean()),
                "lateral_ratio": float(ds[:2].mean() / ds[2]), "lam": float(lam), "shear_modulus": float(g),
                "seconds": time.perf_counter() - t0}

    def _continuum_loads(self) -> None:
        """Loads on the continuum beside the scene's, added before the stepper compiles its
        forms: none here (a saturated run's pore pressure, :mod:`coupling.apps.penetration.
        saturated`)."""

    def _geostatic_loads(self):
        """3D: gravity on the continuum and, on its side, the traction of the geostatic stress
        ``sigma_geo = -rho g (s - z) diag(K0, K0, 1)`` (uniaxial strain, K0 = lam / (lam + 2 mu
        + kappa)): the confining pressure K0 rho g (s - z) on a vertical side.

        The packing's numbers (the unit weight rho g, the surface's height s, K0) enter the
        forms as ``fem.Constant`` (kept in ``self.geostatic``): a float in a form is part of
        its FFCx signature, so each packing compiled the residual and its tangents anew; with
        constants the next packing reuses them (tests/coupling/test_form_reuse.py)."""
        import ufl
        from dolfinx import default_scalar_type, fem

        m, g, domain = self.material_fe, self.prm.gravity, self.problem.domain

        def constant(value):
            return fem.Constant(domain, default_scalar_type(value))

        geo = self.geostatic = SimpleNamespace(unit_weight=constant(m.rho * g), surface=constant(self.surface),
                                               k0=constant(self._geostatic_k0()))
        self.problem.body_force((0.0, 0.0, -m.rho * g))   # (a fem.Constant: ContinuumProblem.body_load)
        xs, n = ufl.SpatialCoordinate(domain), ufl.FacetNormal(domain)
        # sigma_geo . n, not -sigma_h n: the side's facets are not exactly vertical
        sigma_geo = -geo.unit_weight * (geo.surface - xs[2]) * ufl.diag(ufl.as_vector([geo.k0, geo.k0, 1.0]))
        self.problem.traction("side", sigma_geo * n)
        self.k0 = float(geo.k0.value)

    def _geostatic_k0(self) -> float:
        """K0 = lam / (lam + 2 mu + kappa): sigma_h / sigma_v of the continuum under uniaxial strain."""
        m = self.material_fe
        return m.lam / (m.lam + 2 * m.mu + m.kappa)

    def _hold_geostatic_state(self):
        """Prescribed dofs start at w_geo; ghosts and grains move relative to it."""
        iface, w = self.interface, self.problem.w
        iface.set_prescribed(np.concatenate([w.x.array[f.prescribed] for f in iface.fields]))
        self._g_ref = iface.ghost_motion()
        self._q_ref = np.zeros((self.n_grains, 3))
        self._q_ref[iface.free_owned] = iface.fields[0].free.interpolate(w)

    # ---- exchange -----------------------------------------------------------------------
    def _ghost_motion(self):
        """(u, theta) of the ghosts from the FE state, relative to the geostatic state."""
        u, theta = self.interface.ghost_motion()
        if self._g_ref is not None:
            u, theta = u - self._g_ref[0], theta - self._g_ref[1]
        return u, theta

    @property
    def n_steps(self) -> int:
        return int(np.ceil(self.prm.depth / self.prm.velocity / self.dt_fe))

    def run(self, progress=None, steps: int | None = None):
        """Push to ``prm.depth`` (or ``steps`` more FE steps), continuing from the current
        state; returns the history of all steps so far."""
        stop = self.n_steps if steps is None else min(self.n_steps, len(self.history) + steps)
        while len(self.history) < stop:
            self.advance()
            if progress is not None:
                progress(self.history[-1])
        return self.history

    def advance(self) -> dict:
        """One FE step (the DEM sub-cycle, projection, FE solve); returns its history record."""
        check_push(self.prm, self.sim.dt)
        if self.prm.interface == "loose":
            return self._loose_step()
        if self.forces:
            return self._forces_step()
        return self._converged_step()

    def _grain_displacement(self, geostatic: bool = True) -> np.ndarray:
        """The free and ghost grains' displacements (n, dim) the projection reads (collective
        when the grains are distributed); ``geostatic``: with the geostatic state's (3D free
        surface), else from the settled packing alone."""
        dim, n = self.prm.dim, self.n_grains
        x = self.sim.values_of(np.arange(n), "x") if self.distributed else self.sim.p.x[:n]
        u = x[:, :dim] - self.x_ref[:, :dim]
        return u if self._q_ref is None or not geostatic else u + self._q_ref[:, :dim]

    def _cone_force(self) -> np.ndarray:
        """(k, 3) [N]: the grains' forces on the clump's spheres (its own contacts taken out)."""
        f = self.sim.values_of(self.pen_index, "force") if self.distributed else self.sim.p.force[self.pen_index]
        return f - self.clump_internal

    def grain_state(self) -> Particles:
        """Every particle now, in the serial order (collective: distributed grains are gathered
        to every rank)."""
        if not self.distributed:
            return self.sim.p
        g = self.comm.bcast(self.sim.gather(root=0), root=0)
        q = self.particles
        p = Particles(g["x"], g["v"], g["omega"], q.radius, q.mass, q.inertia, q.material, q.kind, q.dim)
        p.force[:], p.torque[:] = g["force"], g["torque"]
        return p

    def _converged_step(self) -> dict:
        """One FE step whose exchange is iterated to ``prm.interface_tol``: the grains are
        rewound to the step's start (``sim.load_state``) and sub-cycled again with the ghosts
        heading for the current FE iterate (no lag), the FE re-solved with the projected
        displacements (only the last FE iterate is committed), the fixed point on the
        prescribed displacements' increment accelerated by IQN-ILS (:class:`coupling.
        interface.IQNILS`, pairs of the last step reused). A step that does not converge in
        ``prm.interface_max_iterations`` keeps its last iterate and is flagged in the history."""
        prm, sim, iface, st, acc = self.prm, self.sim, self.interface, self.stepper, self.accelerator
        ax, k, clock = VERTICAL[prm.dim], len(self.history), time.perf_counter
        t0 = clock()
        saved, depth0, g_prev = sim.state_dict(), self.depth, self.g_prev
        st.predict()
        D = iface.prescribed_values()
        n_u = iface.fields[0].prescribed.size
        D_n, x = D[:n_u].copy(), np.zeros(n_u)
        floor = 1e-6 * prm.radius * np.sqrt(max(iface.comm.allreduce(n_u), 1))
        acc.new_step()
        st.solve()
        t_dem = t_fe = 0.0
        for it in range(1, prm.interface_max_iterations + 1):
            g_next = self._ghost_motion()
            t1 = clock()
            if it > 1:
                sim.load_state(saved)
            ghosts = self._ghosts(g_prev, g_next)
            for servo in self.servos:   # the top plate's speed, held over the sub-cycle
                servo(sim)
            depth = sub_cycle(sim, prm.substeps, (self.pen_index, self.pen0), depth0, prm.velocity,
                              ax, ghosts)
            t2 = clock()
            t_dem += t2 - t1
            target = iface.project_displacement(self._grain_displacement()) - D_n
            new, res = acc.update(x, target)
            if not np.isfinite(res):
                raise CouplingUnstable(f"interface residual is {res} at FE step {k + 1}")
            converged = bool(res < prm.interface_tol or iface.norm(target - x) < floor)
            if converged:
                break
            x = new
            D[:n_u] = D_n + x
            iface.set_prescribed(D)
            st.solve()
            t_fe += clock() - t2
        st.finish()
        # the ghosts of the accepted FE state: g_next unless a solve followed it (no convergence)
        self._g_now = g_next if converged else self._ghost_motion()
        self.depth, self.g_prev = depth, g_next
        mismatch = self._check_ghosts(self._g_now, g_next, k)
        f = self._cone_force()
        self.history.append(cone_record(prm, f, self.parts, self.depth, k + 1, st.t,
                                        interface_mismatch=mismatch, interface_iterations=it,
                                        interface_residual=float(res), interface_converged=converged,
                                        dem_time=t_dem, wall_time=clock() - t0))
        self.step_timings.append({"dem": t_dem, "fe_solve": t_fe, "total": self.history[-1]["wall_time"],
                                  "interface_iterations": it})
        return self.history[-1]

    def _loose_step(self) -> dict:
        """One FE step of the loose exchange: the grains' displacement projected onto the
        prescribed nodes, relaxed by ``prm.relaxation``."""
        iface, n_u = self.interface, self.interface.fields[0].prescribed.size

        def exchange():
            # only the displacement part is prescribed from the grains; phi from the FE itself
            # (grain spins are not a displacement field)
            old = iface.prescribed_values()
            D = old.copy()
            D[:n_u] = iface.project_displacement(self._grain_displacement())
            if self._phi_ref is not None:   # a micromorphic phi: the grains' fitted micro-deformation
                D[n_u:] = self._phi_ref + iface.project_micro_deformation(self._grain_displacement(geostatic=False))
            iface.set_prescribed(old + self.prm.relaxation * (D - old))
            return {}

        return self._staggered_step(exchange)

    def _forces_step(self) -> dict:
        """One FE step of the force-carrying exchange (:mod:`coupling.reactions`): the free
        grains' push on the ghosts averaged over the sub-cycle (time-averaged impulses, not the
        last force: DESIGN's lesson from peers), its increment from the start handed to the FE
        as nodal loads ``N^T f`` (relaxed by ``prm.relaxation``)."""
        prm, rows = self.prm, self.ghost_local
        # the DEM's own sums over its steps (no hook: the serial run keeps its fused loop);
        # distributed, each rank sums the ghosts it owns (the rows of the global ids), added
        # over the ranks after
        sums = (rows.astype(np.int64), np.zeros((len(rows), 3)))

        def exchange():
            total = self.comm.allreduce(sums[1]) if self.distributed else sums[1]
            push = total[:, :prm.dim] / prm.substeps - self.f0
            self.f_applied += prm.relaxation * (push - self.f_applied)
            self.interface.apply(self.f_applied)
            return {"ghost_push": float(np.abs(self.f_applied).sum())}

        return self._staggered_step(exchange, sums=sums)

    def _staggered_step(self, exchange, hook=None, sums=None) -> dict:
        """One FE step of a staggered exchange: one DEM sub-cycle (``hook`` after each DEM
        step; ``sums``: `dem.Simulation.step`'s force sums) with the ghosts heading for the
        last FE state, ``exchange()`` hands the grains to the FE (it returns extra history
        entries), one FE solve."""
        prm, sim, st = self.prm, self.sim, self.stepper
        k, clock = len(self.history), time.perf_counter
        t0 = clock()
        # ghosts head for the last converged FE state (a one-step lag, no extrapolation:
        # extrapolating the FE acceleration amplifies the grains' noise)
        g_prev, g_next = self.g_prev, (self._ghost_motion() if self._g_now is None else self._g_now)
        t_ghosts = clock() - t0
        st.predict()
        t_dem = clock()
        ghosts = self._ghosts(g_prev, g_next)
        for servo in self.servos:   # the top plate's speed, held over the sub-cycle
            servo(sim)
        step = self._before_sub_cycle(hook)
        if sums is not None:
            step["sums"] = sums
        self.depth = sub_cycle(sim, prm.substeps, (self.pen_index, self.pen0), self.depth,
                               prm.velocity, VERTICAL[prm.dim], ghosts, **step)
        t1 = clock()
        t_dem = t1 - t_dem
        extra = exchange()
        t2 = clock()
        st.solve()
        st.finish()
        t3 = clock()
        g_new = self._g_now = self._ghost_motion()   # the next step's target
        t4 = clock()
        mismatch = self._check_ghosts(g_new, g_next, k)
        # the ghosts continue from where the grains saw them (no jump between FE steps)
        self.g_prev = g_next
        f = self._cone_force()
        self.history.append(cone_record(prm, f, self.parts, self.depth, k + 1, st.t,
                                        interface_mismatch=mismatch, dem_time=t_dem, **extra,
                                        wall_time=clock() - t0))
        self.step_timings.append({"ghost_motion": t_ghosts + t4 - t3, "dem": t_dem,
                                  "projection": t2 - t1, "fe_solve": t3 - t2,
                                  "total": self.history[-1]["wall_time"]})
        return self.history[-1]

    def _ghosts(self, g_prev, g_next) -> GhostMotion:
        """The ghosts' motion over the FE step from the continuum's (u, theta) at them, ``g_prev``
        to ``g_next``: translated by u and spun by theta (the micropolar rotation, a
        micromorphic phi's axial vector)."""
        return GhostMotion(self.ghost_local, self.x_ref[self.ghost_local], g_prev[0], g_next[0],
                           self.dt_fe, theta_start=g_prev[1], theta_end=g_next[1])

    def _before_sub_cycle(self, hook) -> dict:
        """Called once before each FE step's DEM sub-cycle; returns the keyword arguments of
        its `dem.Simulation.step` call: the hook of its DEM steps (``hook``: the exchange's
        own), and what a subclass adds. A saturated run solves its fluid here and adds the
        fluid's drag or response and its steps in between (:mod:`coupling.apps.penetration.
        saturated`)."""
        return {"hook": hook}

    def _refined_depth(self) -> float:
        """Depth [m] down to which the chamber's mesh is refined to the window's element
        size: the window's (a window that moves needs more)."""
        return self.prm.window_depth

    # ---- checkpoints --------------------------------------------------------------------
    def _check_ghosts(self, g_new, g_predicted, k: int) -> float:
        """The interface mismatch of FE step ``k`` (ghost motion after the solve against the
        motion the grains were driven with); raises :class:`CouplingUnstable` when a ghost
        moved more than twice as far as the cone has pushed: the ghosts sit in the cone's far
        field, so that means the exchange is diverging, not that the sand flows."""
        prm = self.prm
        mismatch = float(np.linalg.norm(g_new[0] - g_predicted[0])
                         / max(np.linalg.norm(g_new[0]), 1e-30))
        ghost_max = float(np.abs(g_new[0]).max(initial=0.0))
        bound = 2 * self.depth + 2 * prm.radius
        if not np.isfinite(ghost_max) or ghost_max > bound:
            raise CouplingUnstable(
                f"coupling unstable at depth {self.depth:.4g} m (FE step {k + 1}): ghost "
                f"displacement {ghost_max:.3g} m exceeds twice the cone's travel ({bound:.3g} m); "
                f"reduce coupling.relaxation ({prm.relaxation}), coupling.substeps "
                f"({prm.substeps}) or penetrator.velocity ({prm.velocity} m/s)")
        return mismatch

    def save_checkpoint(self, directory, meta: dict | None = None) -> Path:
        """Write what :meth:`run` needs to continue exactly (collective): the grains' state
        with contact history, the settled reference, the continuum constants, the FE state
        of the stepper (one file per rank), the ghosts' last motion, depth and history.
        Atomic (:func:`coupling.checkpoints.write_checkpoint`): written beside ``directory``,
        then renamed into place, the previous one kept as ``<directory>.prev``; ``meta``
        (e.g. the run's fingerprint) goes into its manifest."""
        from coupling.checkpoints import write_checkpoint

        comm, st = self.comm, self.stepper
        step = len(self.history)
        # the grains: one file (distributed: the positions, gathered, and the cuts; each
        # rank's part of the run in a file of its own)
        if self.distributed:
            part = self.sim.state_dict()
            grains = {"p.x": self.grain_state().x,
                      **{f"owner.{k}": getattr(self.owner, k) for k in ("axis", "cut", "below", "above")}}
        else:
            part, grains = None, _dem_state(self.sim)

        def files(tmp: Path) -> list[str]:
            own = []
            if part is not None:
                own = [f"grains_rank{comm.rank}_of{comm.size}.npz"]
                np.savez(tmp / own[0], **part)
            name = f"continuum_rank{comm.rank}_of{comm.size}.npz"
            np.savez(tmp / name, w=self.problem.w.x.array, w_old=st.w_old.x.array, v=st.v.x.array,
                     a=st.a.x.array, g=self.interface.g.x.array, last_good=self.problem.last_good,
                     **{f"qp.{k}": v for k, v in self.problem.state.state_dict().items()},
                     **{f"iqn.{k}": v for k, v in self.accelerator.state_dict().items()})
            own += self._checkpoint_files(tmp)
            if comm.rank != 0:
                return [name] + own
            forces = {} if self.f0 is None else {"f0": self.f0, "f_applied": self.f_applied}
            np.savez(tmp / "grains.npz", **grains, x_ref=self.x_ref, pen0=self.pen0,
                     g_prev_u=self.g_prev[0], g_prev_theta=self.g_prev[1], **forces)
            state = {"step": step, "depth": self.depth, "t": st.t,
                     "ranks": comm.size, "surface": self.surface,
                     "material": asdict(self.material_fe), "packing": self.contact_stats,
                     "initial_stress": getattr(self, "initial_stress", None),
                     "plate_area": self.servos[0].area if self.servos else None,
                     "history": self.history}
            (tmp / "state.json").write_text(json.dumps(state, indent=1))
            return [name, "grains.npz", "state.json"] + own

        return write_checkpoint(directory, step, comm, files, meta=meta)

    def _displacement_interface(self) -> CouplingInterface:
        """The loose and iterated exchanges' interface, its basis at the grains' reference
        positions ``x_ref``. Window nodes with few grains in their support (the free surface)
        stay FE dofs: an ill-conditioned projection there would amplify the grains' noise."""
        return CouplingInterface(self.problem, self.x_ref, self.kinds, self.regions, min_support=0.3)

    def _accelerator(self) -> IQNILS:
        """The iterated exchange's accelerator on the interface (the last step's pairs
        reused: the next step's map is nearly the same)."""
        return IQNILS(self.interface, self.prm.relaxation, IQNOptions(reuse=1))

    def _checkpoint_files(self, tmp: Path) -> list[str]:
        """A subclass's own files of a checkpoint, written into ``tmp`` on every rank (their
        names; :meth:`save_checkpoint` calls it collectively). None here."""
        return []

    def _read_checkpoint(self, directory: Path) -> dict:
        """The checkpoint in ``directory``, validated against its manifest (every file's
        sha256); a ``FileNotFoundError`` naming what is wrong otherwise."""
        from coupling.checkpoints import validate

        comm = self.comm
        manifest, reason = validate(directory) if comm.rank == 0 else (None, "")
        manifest, reason = comm.bcast((manifest, reason), root=0)
        if manifest is None:
            raise FileNotFoundError(f"no complete checkpoint in {directory} ({reason})")
        if manifest.get("ranks") != comm.size:
            ranks = manifest.get("ranks")
            raise FileNotFoundError(f"the checkpoint in {directory} was written on {ranks} "
                                    f"rank(s); restart with mpiexec -n {ranks}")
        try:
            state = json.loads((directory / "state.json").read_text())
            grains = dict(np.load(directory / "grains.npz"))
            fe = dict(np.load(directory / f"continuum_rank{comm.rank}_of{comm.size}.npz"))
            material = MicropolarMaterial(**state["material"])
            missing = [k for k in ("t", "depth", "history", "packing", "surface") if k not in state]
            missing += [k for k in ("x_ref", "pen0", "g_prev_u", "g_prev_theta", "p.x")
                        if k not in grains]
            if missing:
                raise KeyError(", ".join(missing))
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise FileNotFoundError(f"the checkpoint in {directory} is not a penetration "
                                    f"checkpoint or is damaged ({type(err).__name__}: "
                                    f"{err})") from None
        split = None
        if self.prm.distribute_grains and comm.size > 1:
            # each rank's part of the distributed run, loaded once it is built
            try:
                split = dict(np.load(directory / f"grains_rank{comm.rank}_of{comm.size}.npz"))
            except OSError as err:
                raise FileNotFoundError(f"the checkpoint in {directory} has no grains of rank "
                                        f"{comm.rank} ({err}): written without distribute_grains?") from None
            _check_particle_count(self.sim, grains)
        else:
            _load_dem_state(self.sim, grains)
        self.x_ref, self.pen0 = grains["x_ref"], grains["pen0"]
        self.material_fe = material
        self.contact_stats = state["packing"]
        s0 = state.get("initial_stress")
        self.initial_stress = None if s0 is None else tuple(s0)
        self.surface = state["surface"]
        return {"state": state, "grains": grains, "fe": fe, "grains_rank": split}

    def _restore_run(self, saved: dict) -> None:
        st, fe, state = self.stepper, saved["fe"], saved["state"]
        for target, name in ((self.problem.w, "w"), (st.w_old, "w_old"), (st.v, "v"), (st.a, "a"),
                             (self.interface.g, "g")):
            if target.x.array.shape != fe[name].shape:
                raise ValueError(f"checkpoint field {name} has {fe[name].shape} values, the "
                                 f"mesh {target.x.array.shape}: different parameters or mesh")
            target.x.array[:] = fe[name]
        self.problem.last_good[:] = fe["last_good"]
        if self.problem.state:
            self.problem.state.load_state({k[3:]: v for k, v in fe.items() if k.startswith("qp.")})
        if "iqn.step" in fe:
            self.accelerator.load_state({k[4:]: v for k, v in fe.items() if k.startswith("iqn.")})
        st.t = state["t"]
        self.depth = state["depth"]
        self.history = state["history"]
        g = saved["grains"]
        self.g_prev = (g["g_prev_u"], g["g_prev_theta"])
        if self.forces:
            self.f0, self.f_applied = g["f0"].copy(), g["f_applied"].copy()
        self.log(f"restarted from step {state['step']} (depth {self.depth:.4g} m)")
