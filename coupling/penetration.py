"""2D coupled cone penetration: a DE window of frictional grains around a rigid cone pushed
at constant velocity, inside a micropolar FE chamber, joined through an overlap band.

Set-up (plane strain, per unit thickness):

1. the FE chamber ``[-W/2, W/2] x [-H, 0]`` is meshed with gmsh (refined toward the window);
2. grains fill the window and its ghost band on a jittered hexagonal lattice and settle
   under gravity with the band's grains held (they are the ghosts: the container);
3. the continuum takes the settled packing's stiffness from its contact stiffness
   (``k_n = 3/2 F_n / delta`` of Hertz at the settled overlaps, mapped to the lattice
   constants of :func:`dem.bonded.hexagonal_lattice_micropolar` and scaled by the
   coordination number over 6) and the packing's density; it models the increment from
   the geostatic state (no gravity on the FE side);
4. the cone (60 degree apex, a rigid clump of ghost disks on its outline) moves down at
   constant velocity; per FE step the DEM takes ``substeps`` explicit steps with the band's
   ghosts following the FE displacement (interpolated in time from the last two FE states),
   the free grains' displacements are projected onto the window's FE nodes (eq. 79-90) and
   the FE step is solved (generalized-alpha). One Gauss-Seidel pass per FE step (loose
   coupling), with the interface residual reported.

Outputs: tip resistance ``q_c`` (vertical force on the cone part / cone width) and sleeve
friction (tangential force on the shaft / its embedded length) against depth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np

from coupling.interface import CouplingInterface
from coupling.regions import Box, CouplingRegions
from dem import GHOST, ContactMaterial, Particles, Simulation
from dem.bonded import hexagonal_lattice, hexagonal_lattice_micropolar
from granfe.dynamics import GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

__all__ = ["PenetrationParameters", "CoupledPenetration", "DemPenetration", "cone_record",
           "CouplingUnstable"]


class CouplingUnstable(RuntimeError):
    """The DE x FE exchange diverged (ghost motion beyond its bound, or NaN)."""


@dataclass(frozen=True)
class PenetrationParameters:
    """All lengths in m, times in s. Defaults: a 2 cm cone into ~1000 grains of 1.5 mm."""

    chamber_width: float = 0.3
    chamber_depth: float = 0.2
    window_half_width: float = 0.04
    window_depth: float = 0.08
    ghost_width: float = 2.5          # grain diameters
    handshake: float = 2.0            # elements (1 is at the edge of stability)
    element_size_window: float = 0.008
    element_size_far: float = 0.04
    radius: float = 1.5e-3
    jitter: float = 0.1               # radius reduction, fraction (no initial overlap)
    kn: float = 2.0e5                 # linear contact stiffness [N/m per m thickness]
    kt_over_kn: float = 0.5
    nu: float = 0.25
    density: float = 2650.0
    friction: float = 0.5
    restitution: float = 0.5
    cone_radius: float = 0.01
    apex_deg: float = 60.0
    velocity: float = 0.2
    depth: float = 0.04
    substeps: int = 50
    relaxation: float = 0.3           # of the prescribed values D^ per FE step
    settle_time: float = 0.3
    gravity: float = 9.81
    seed: int = 1

    def __post_init__(self):
        for name in ("chamber_width", "chamber_depth", "window_half_width", "window_depth",
                     "ghost_width", "handshake", "element_size_window", "element_size_far",
                     "radius", "kn", "density", "cone_radius", "velocity", "depth", "settle_time"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if self.window_half_width <= 2 * self.cone_radius:
            raise ValueError(f"window_half_width = {self.window_half_width} must exceed twice the "
                             f"cone radius ({self.cone_radius}): the cone must stay inside the window")
        if self.depth + self.cone_radius * 2 >= self.window_depth:
            raise ValueError(f"depth = {self.depth} m leaves the cone too close to the window base "
                             f"(window_depth = {self.window_depth} m)")
        if self.window_half_width + (self.ghost_width + 1) * 2 * self.radius >= self.chamber_width / 2:
            raise ValueError("the window and its ghost band must lie inside the chamber")
        if not 0 <= self.jitter < 0.5:
            raise ValueError(f"jitter must lie in [0, 0.5), got {self.jitter!r}")
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps!r}")


def cone_clump(radius_cone, apex_deg, shaft_length, r_grain):
    """Centres (k, 3) of ghost disks on a cone-and-shaft outline (tip at the origin), the
    disks' radius, and a mask of the ones on the cone (not the shaft)."""
    rc = 0.5 * r_grain
    h_cone = radius_cone / np.tan(np.radians(apex_deg) / 2)
    pts, on_cone = [], []
    for side in (-1, 1):
        s = np.arange(0.0, np.hypot(radius_cone, h_cone), rc)
        t = s / np.hypot(radius_cone, h_cone)
        pts.append(np.column_stack([side * t * radius_cone, t * h_cone]))
        on_cone.append(np.ones(len(s), bool))
        ys = np.arange(h_cone + rc, h_cone + shaft_length, rc)
        pts.append(np.column_stack([np.full_like(ys, side * radius_cone), ys]))
        on_cone.append(np.zeros(len(ys), bool))
    xy = np.vstack(pts)
    keep = np.unique(np.round(xy / (1e-6 * rc)), axis=0, return_index=True)[1]
    xy, cone = xy[np.sort(keep)], np.concatenate(on_cone)[np.sort(keep)]
    # centres sit inside the outline by rc so that the envelope is the cone surface
    return np.column_stack([xy, np.zeros(len(xy))]), rc, cone


def cone_record(prm, force_on_cone, on_cone, depth, step, t, **extra) -> dict:
    """History entry: tip force on the cone part, q_c = F / cone width, sleeve friction."""
    tip_force = float(force_on_cone[on_cone, 1].sum())
    sleeve = float(force_on_cone[~on_cone, 1].sum())
    embedded = max(depth - prm.cone_radius / np.tan(np.radians(prm.apex_deg) / 2), 0.0)
    return {"step": step, "time": t, "depth": depth, "tip_force": tip_force,
            "q_c": tip_force / (2 * prm.cone_radius), "sleeve_force": sleeve,
            "f_s": sleeve / (2 * embedded) if embedded > 0 else 0.0, **extra}


def _cone_and_material(prm, top):
    """The cone clump above ``top`` and the grains' contact material."""
    shaft = prm.depth + 3 * prm.cone_radius
    pen, r_pen, on_cone = cone_clump(prm.cone_radius, prm.apex_deg, shaft, prm.radius)
    tip0 = float(top + prm.radius + r_pen + 0.1 * prm.radius)
    pen[:, 1] += tip0 + r_pen
    # disks of unit thickness: a linear law (a line contact has no Hertz radius law that
    # the sphere formulas would give); E only enters the time-step estimate
    material = ContactMaterial(E=prm.kn, nu=prm.nu, density=prm.density, friction=prm.friction,
                               restitution=prm.restitution, law="linear", kn=prm.kn,
                               kt=prm.kt_over_kn * prm.kn)
    return pen, r_pen, on_cone, material


class DemPenetration:
    """The same penetration fully as DEM: grains fill the whole chamber, held by walls
    (no continuum objects are built). The reference for :class:`CoupledPenetration`."""

    def __init__(self, prm: PenetrationParameters, log=print):
        from dem import PlaneWall

        self.prm = prm
        rng = np.random.default_rng(prm.seed)
        W, H = prm.chamber_width, prm.chamber_depth
        x = hexagonal_lattice((-W / 2, -H), (W / 2, 0.0), prm.radius)
        radius = prm.radius * (1 - prm.jitter * rng.random(len(x)))
        Particles.spheres(x, radius, prm.density, dim=2).check_overlaps()
        pen, r_pen, self.on_cone, material = _cone_and_material(prm, x[:, 1].max())
        self.pen0 = pen.copy()
        n = len(x)
        p = Particles.spheres(np.vstack([x, pen]), np.concatenate([radius, np.full(len(pen), r_pen)]),
                              prm.density, dim=2,
                              kind=np.concatenate([np.zeros(n), np.full(len(pen), GHOST)]).astype(np.int8))
        walls = [PlaneWall((-W / 2, 0, 0), (1, 0, 0)), PlaneWall((W / 2, 0, 0), (-1, 0, 0)),
                 PlaneWall((0, -H, 0), (0, 1, 0))]
        self.n_grains, self.pen_index = n, np.arange(n, n + len(pen))
        self.sim = Simulation(p, material, walls=walls, gravity=(0.0, -prm.gravity, 0.0),
                              allow_overlap=True)
        self.sim.compute_forces(update_history=False)
        self.clump_internal = self.sim.p.force[self.pen_index].copy()
        t0 = time.perf_counter()
        self.sim.step(int(np.ceil(prm.settle_time / self.sim.dt)))
        log(f"full DEM: settled {n} grains in {time.perf_counter() - t0:.1f} s")
        self.history: list[dict] = []

    def run(self, progress=None):
        prm, sim = self.prm, self.sim
        p = sim.p
        block = prm.substeps * sim.dt
        n_steps = int(np.ceil(prm.depth / prm.velocity / block))
        depth, t = 0.0, 0.0
        for k in range(n_steps):
            t0 = time.perf_counter()
            for _ in range(prm.substeps):
                depth += prm.velocity * sim.dt
                p.x[self.pen_index] = self.pen0 - depth * np.array([0.0, 1.0, 0.0])
                p.v[self.pen_index] = (0.0, -prm.velocity, 0.0)
                sim.step(1)
            t += block
            f = p.force[self.pen_index] - self.clump_internal
            self.history.append(cone_record(prm, f, self.on_cone, depth, k + 1, t,
                                            wall_time=time.perf_counter() - t0))
            if progress is not None:
                progress(self.history[-1])
        return self.history


class CoupledPenetration:
    """Builds and runs the coupled 2D penetration (see the module docstring)."""

    def __init__(self, prm: PenetrationParameters, comm, log=print):
        from meshes.penetration import build_chamber

        self.prm, self.comm, self.log = prm, comm, log
        rng = np.random.default_rng(prm.seed)
        d = 2 * prm.radius
        band = prm.ghost_width * d
        a, b = prm.window_half_width, prm.window_depth
        # ---- grains: jittered lattice over window + band, then settle with the band held
        lattice = hexagonal_lattice((-a - band, -b - band), (a + band, 0.0), prm.radius)
        radius = prm.radius * (1 - prm.jitter * rng.random(len(lattice)))
        self.regions = CouplingRegions(Box((-a, -b), (a, 2 * b)), ghost_width=band,
                                       handshake=prm.handshake * prm.element_size_window)
        kinds = self.regions.particle_kinds(lattice)
        keep = kinds >= 0
        self.x_grains, self.kinds = lattice[keep], kinds[keep].astype(np.int8)
        radius = radius[keep]
        n = len(self.x_grains)
        pen, r_pen, self.on_cone, self.material = _cone_and_material(prm, self.x_grains[:, 1].max())
        self.pen0 = pen.copy()
        x = np.vstack([self.x_grains, pen])
        r = np.concatenate([radius, np.full(len(pen), r_pen)])
        kind = np.concatenate([np.where(self.kinds == 1, GHOST, 0), np.full(len(pen), GHOST)]).astype(np.int8)
        Particles.spheres(self.x_grains, radius, prm.density, dim=2).check_overlaps()
        p = Particles.spheres(x, r, prm.density, dim=2, kind=kind)
        self.n_grains, self.pen_index = n, np.arange(n, n + len(pen))
        # the cone's disks overlap each other by construction (a smooth rigid outline)
        self.sim = Simulation(p, self.material, gravity=(0.0, -prm.gravity, 0.0),
                              allow_overlap=True)
        # the clump's own (constant) internal forces, to subtract from the cone's resultant
        self.sim.compute_forces(update_history=False)
        self.clump_internal = self.sim.p.force[self.pen_index].copy()
        t0 = time.perf_counter()
        self.sim.step(int(np.ceil(prm.settle_time / self.sim.dt)))
        e = self.sim.energy()
        log(f"settled {n} grains in {time.perf_counter() - t0:.1f} s "
            f"({self.sim.nsteps} steps of {self.sim.dt:.3g} s), kinetic energy "
            f"{e['kinetic_translational']:.3g} J")
        self.x_ref = self.sim.p.x[:n].copy()
        # ---- continuum: chamber, stiffness from the settled contacts
        data = build_chamber(comm, 2, width=prm.chamber_width, depth=prm.chamber_depth,
                             window_width=2 * (a + band), window_depth=b + band,
                             h_window=prm.element_size_window, h_far=prm.element_size_far)
        # the continuum reaches the highest settled grain centre (every grain inside the mesh)
        self.surface = float(self.x_ref[:, 1].max() + 1e-3 * prm.radius)
        data.mesh.geometry.x[:, 1] += self.surface
        self.material_fe, self.contact_stats = self._continuum_material()
        names = {k: tag for k, (dim, tag) in data.physical_groups.items() if dim == 1}
        self.problem = MicropolarProblem(data.mesh, self.material_fe, facet_tags=data.facet_tags,
                                         tag_names=names, degree=(1, 1), prefix="cpt_")
        self.problem.fix("bottom", "u")
        self.problem.fix("bottom", "phi")
        self.problem.fix("left", "u_x")
        self.problem.fix("right", "u_x")
        coupled = np.arange(n)
        # window nodes with few grains in their support (the free surface) stay FE dofs: an
        # ill-conditioned projection there would amplify the grains' noise
        self.interface = CouplingInterface(self.problem, self.x_ref, self.kinds, self.regions,
                                           min_support=0.3)
        self.free_local = np.flatnonzero(self.kinds == 0)
        self.ghost_local = np.flatnonzero(self.kinds == 1)
        del coupled
        self.dt_fe = prm.substeps * self.sim.dt
        self.stepper = GeneralizedAlpha(self.problem, self.dt_fe, rho_inf=0.8)
        self.history: list[dict] = []

    def _continuum_material(self):
        """Micropolar constants of the settled packing: the bonded-lattice constants of
        (kn, kt) scaled by the coordination number over 6, the packing's density."""
        sim, prm = self.sim, self.prm
        i, j = sim.contacts()
        grains = (i < self.n_grains) & (j < self.n_grains)
        z = 2 * int(grains.sum()) / max(self.n_grains, 1)
        scale = z / 6.0
        kn, kt = prm.kn, prm.kt_over_kn * prm.kn
        c = hexagonal_lattice_micropolar(scale * kn, scale * kt, 0.1 * scale * kt * (2 * prm.radius) ** 2)
        r = sim.p.radius[: self.n_grains]
        lo, hi = self.x_ref[:, :2].min(0), self.x_ref[:, :2].max(0)
        rho = prm.density * np.pi * np.sum(r**2) / np.prod(hi - lo)
        mat = MicropolarMaterial(**c, rho=rho, j=prm.radius**2 / 2)
        return mat, {"contacts": int(grains.sum()), "coordination": z, "density": rho}

    def _ghost_positions(self, w_start, w_end, frac):
        u0, _ = w_start
        u1, _ = w_end
        return self.x_ref[self.ghost_local] + np.column_stack([(1 - frac) * u0 + frac * u1,
                                                                np.zeros(len(u0))])

    def run(self, progress=None):
        prm, sim, iface, st = self.prm, self.sim, self.interface, self.stepper
        p = sim.p
        n_steps = int(np.ceil(prm.depth / prm.velocity / self.dt_fe))
        g_prev = iface.ghost_motion()
        pen_v = np.array([0.0, -prm.velocity, 0.0])
        depth = 0.0
        for k in range(n_steps):
            t0 = time.perf_counter()
            # ghosts head for the last converged FE state (a one-step lag, no extrapolation:
            # extrapolating the FE acceleration amplifies the grains' noise)
            g_next = iface.ghost_motion()
            st.predict()
            for s in range(1, prm.substeps + 1):
                frac = s / prm.substeps
                p.x[self.ghost_local] = self._ghost_positions(g_prev, g_next, frac)
                p.v[self.ghost_local, :2] = (g_next[0] - g_prev[0]) / self.dt_fe
                depth += prm.velocity * sim.dt
                p.x[self.pen_index] = self.pen0 + (-depth) * np.array([0.0, 1.0, 0.0])
                p.v[self.pen_index] = pen_v
                sim.step(1)
            u = p.x[: self.n_grains, :2] - self.x_ref[:, :2]
            theta = np.zeros(self.n_grains)   # grain spins are not a displacement field: phi free
            D = iface.project(u, theta)
            # only the displacement part is prescribed from the grains; phi from the FE itself
            n_u = iface.fields[0].prescribed.size
            old = iface.prescribed_values()
            D[n_u:] = old[n_u:]
            iface.set_prescribed(old + prm.relaxation * (D - old))
            st.solve()
            st.finish()
            g_new = iface.ghost_motion()
            mismatch = float(np.linalg.norm(g_new[0] - g_next[0]) / max(np.linalg.norm(g_new[0]), 1e-30))
            ghost_max = float(np.abs(g_new[0]).max(initial=0.0))
            # the ghosts sit in the far field of the cone: moving more than twice as far as the
            # cone has pushed means the exchange is diverging, not that the sand flows
            bound = 2 * depth + 2 * prm.radius
            if not np.isfinite(ghost_max) or ghost_max > bound:
                raise CouplingUnstable(
                    f"coupling unstable at depth {depth:.4g} m (FE step {k + 1}): ghost displacement "
                    f"{ghost_max:.3g} m exceeds twice the cone's travel ({bound:.3g} m); reduce "
                    f"coupling.relaxation ({prm.relaxation}), coupling.substeps ({prm.substeps}) or "
                    f"penetrator.velocity ({prm.velocity} m/s)")
            # the ghosts continue from where the grains saw them (no jump between FE steps)
            g_prev = g_next
            f = p.force[self.pen_index] - self.clump_internal   # forces of the grains only
            self.history.append(cone_record(prm, f, self.on_cone, depth, k + 1, st.t,
                                            interface_mismatch=mismatch,
                                            wall_time=time.perf_counter() - t0))
            if progress is not None:
                progress(self.history[-1])
        return self.history
