"""A representative volume element (RVE) of grains as a material point (seed 004 §2.2, §4).

A periodic cell of spheres (3D) or disks (2D, unit thickness) in a `dem.periodic.PeriodicCell`
is driven quasi-statically by a macroscopic strain increment or by mixed control (any
components of the symmetric stress prescribed, the others as strain: seed 004 eq. 46 and
the GEM algorithm of §2.2.5), and returns the Love-Weber stress (`dem.periodic.cell_stress`)
and a tangent.

Conventions: stress tension positive [Pa], strain extension positive, ``eps = sym(F) - I``
with ``F = h h_ref^-1`` the cell's deformation since the reference (small strains; the cell
is driven by a symmetric velocity gradient, so F stays symmetric). Symmetric tensors travel
as Mandel vectors, (xx, yy, zz, sqrt2 yz, sqrt2 xz, sqrt2 xy) in 3D and (xx, yy, sqrt2 xy) in
2D, so that ``sigma : eps = s . e`` and tangents are plain (k, k) matrices.

Quasi-static solution by dynamic relaxation (GEM solves equilibrium directly; DEM relaxes to
it): local non-viscous damping (`_local_damping`, coefficient ``damping``; its work is not
booked in the Simulation's energy ledger), and every ``window`` steps a servo sets the
velocity gradient. Strain-controlled components move at a constant rate over
the ramp; stress-controlled ones take the strain that the affine contact stiffness
(`RVE.affine_stiffness`, stiffer than the packing: the servo under-corrects rather than
overshoots) says closes ``gain`` of the stress error in one window, capped at ``strain_rate``
a step; each component's gain halves when its error changes sign and grows by a quarter a
window when it does not (`_adapt`). A step has converged when the unbalanced-force ratio
(`RVE.unbalanced_force_ratio`) is below ``force_tol`` and every prescribed stress component
is within ``stress_tol`` x the mean pressure of its target.

Tangent: numerical, by finite perturbation (`RVE.tangent`: forward or central differences
of relaxed strain-controlled runs of size delta, from the state now, restored afterwards);
`RVE.affine_stiffness` is the contact (Voigt) estimate, an upper bound, exact for a lattice
whose grains are centres of symmetry.

Trial / commit / restore: `RVE.commit` keeps a `state_dict` (the Simulation's, bit for bit,
plus the strain reference); `RVE.restore` loads it back, so a rejected macro iteration
costs only its own steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from dem.contact import P_KN, P_KT, ContactMaterial
from dem.errors import DemError
from dem.integrate import Simulation
from dem.packing import random_packing
from dem.periodic import PeriodicCell
from dem.state import Particles

__all__ = ["COMPONENTS", "RVE", "ConvergenceError", "Grains", "QuasiStatic", "from_mandel",
           "to_mandel"]

SQ2 = math.sqrt(2.0)
COMPONENTS = {3: ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)), 2: ((0, 0), (1, 1), (0, 1))}
"""Tensor index pairs of the Mandel components, by dimension."""


def to_mandel(t, dim: int = 3) -> np.ndarray:
    """Mandel vector (6,) in 3D / (3,) in 2D of a symmetric tensor t (3, 3) or (dim, dim)."""
    t = np.asarray(t, float)
    return np.array([t[i, j] * (1.0 if i == j else SQ2) for i, j in COMPONENTS[dim]])


def from_mandel(v, dim: int = 3) -> np.ndarray:
    """Symmetric tensor (3, 3) of a Mandel vector (6,) / (3,) (zeros outside dim x dim)."""
    t = np.zeros((3, 3))
    for a, (i, j) in enumerate(COMPONENTS[dim]):
        t[i, j] = t[j, i] = v[a] if i == j else v[a] / SQ2
    return t


def _love_weber(contacts, volume) -> np.ndarray:
    """1/V sym(sum_c b (x) f) (3, 3) [Pa] of `Simulation.contact_forces(return_branch=True)`
    (what `dem.periodic.cell_stress` returns, without evaluating the forces again)."""
    t = np.einsum("ck,cl->kl", contacts[2], contacts[1]) / volume
    return 0.5 * (t + t.T)


@njit(cache=True)
def _local_damping(v, omega, force, torque, mass, inertia, kind, a_dt):
    """Local non-viscous damping (Cundall, as in PFC) as an impulse before a step: each
    velocity component of a FREE grain moves towards 0 by a_dt |F| / m (a_dt = alpha dt,
    F the force of the last pass; spins by a_dt |T| / I), never past it. It acts on the
    unbalanced force only: no drag on a packing that creeps through equilibria."""
    for i in range(v.shape[0]):
        if kind[i] != 0:
            continue
        for c in range(3):
            dv = a_dt * abs(force[i, c]) / mass[i]
            v[i, c] = max(v[i, c] - dv, 0.0) if v[i, c] > 0 else min(v[i, c] + dv, 0.0)
            dw = a_dt * abs(torque[i, c]) / inertia[i]
            omega[i, c] = max(omega[i, c] - dw, 0.0) if omega[i, c] > 0 \
                else min(omega[i, c] + dw, 0.0)


def _adapt(gain, e, e_prev, grow=1.25, most=100.0):
    """Servo gains (per stress component): halved where the error changed sign since the
    last window (overshoot), grown by ``grow`` where it did not (the packing is softer than
    the affine stiffness says: near jamming or in flow by far), at most ``most``."""
    if e_prev is None:
        return gain
    return np.where(e * e_prev < 0, 0.5 * gain, np.minimum(grow * gain, most))


def _require(obj, name, ok, rng):
    val = getattr(obj, name)
    if not ok(val):
        raise ValueError(f"{type(obj).__name__}.{name} must be {rng}, got {val!r}")


def _positive(a):
    return isinstance(a, (int, float)) and math.isfinite(a) and a > 0


@dataclass(frozen=True)
class Grains:
    """Grains of an RVE, SI units (defaults: seed 004 §4.1, linear springs).

    n: about this many spheres/disks (> 1); dim 2 or 3; d_min, d_max: diameters [m]
    (uniform radii); kn, kt: normal / tangential spring constants [N/m] (kt >= 0);
    friction: Coulomb coefficient (>= 0); density [kg/m^3] (sets the time scale only);
    restitution in (0, 1] (contact dashpots); fraction: solid fraction of the initial gas,
    in (0, 0.35] 3D / (0, 0.5] 2D (random sequential addition); safety: dt / critical dt
    in (0, 0.3]; seed: of the packing; consolidation_friction: the friction while the gas
    is compressed to p0 (None: ``friction``; seed 004 gives no protocol; a lower one makes
    a denser packing, but frictionless packings near jamming creep for long under stress
    control; the grains' friction takes over at p0).
    """

    n: int = 300
    dim: int = 3
    d_min: float = 3.0e-5
    d_max: float = 7.0e-5
    kn: float = 1.0e5
    kt: float = 7.0e4
    friction: float = math.tan(math.radians(15.0))
    density: float = 2650.0
    restitution: float = 0.3
    fraction: float = 0.35
    safety: float = 0.1
    seed: int = 0
    consolidation_friction: float | None = None

    def __post_init__(self):
        _require(self, "n", lambda a: isinstance(a, int) and a > 1, "an integer > 1")
        _require(self, "dim", lambda a: a in (2, 3), "2 or 3")
        _require(self, "d_min", _positive, "> 0 m")
        _require(self, "d_max", lambda a: _positive(a) and a >= self.d_min, ">= d_min [m]")
        for name in ("kn", "density"):
            _require(self, name, _positive, "> 0")
        _require(self, "kt", lambda a: math.isfinite(a) and a >= 0, ">= 0 N/m")
        _require(self, "friction", lambda a: math.isfinite(a) and a >= 0, ">= 0")
        _require(self, "consolidation_friction",
                 lambda a: a is None or (math.isfinite(a) and a >= 0), "None or >= 0")
        _require(self, "restitution", lambda a: 0 < a <= 1, "in (0, 1]")
        top = 0.35 if self.dim == 3 else 0.5
        _require(self, "fraction", lambda a: 0 < a <= top, f"in (0, {top}]")
        _require(self, "safety", lambda a: 0 < a <= 0.3, "in (0, 0.3]")

    def material(self) -> ContactMaterial:
        """The linear-spring contact material (E, nu are not used by the linear law)."""
        return ContactMaterial(E=1e9, nu=0.25, density=self.density, friction=self.friction,
                               restitution=self.restitution, law="linear", kn=self.kn,
                               kt=self.kt)

    def cell_side(self) -> float:
        """Side [m] of the square/cube holding n grains at the solid fraction ``fraction``."""
        a, b = 0.5 * self.d_min, 0.5 * self.d_max
        if self.dim == 3:
            mean = math.pi * 4.0 / 3.0 * (a**3 if a == b else (b**4 - a**4) / (4 * (b - a)))
        else:
            mean = math.pi * (a**2 if a == b else (b**3 - a**3) / (3 * (b - a)))
        return (self.n * mean / self.fraction) ** (1.0 / self.dim)


@dataclass(frozen=True)
class QuasiStatic:
    """Settings of the quasi-static solution (dimensionless unless stated).

    force_tol: unbalanced-force ratio to reach, in (0, 1); stress_tol: largest error of a
    prescribed stress component over the mean pressure, in (0, 1); damping: coefficient
    alpha of the local non-viscous damping, in [0, 1) (PFC's default 0.7; a viscous one
    would drag the grains that the cell pushes together, a stress rho c eps_dot d^2 that
    exceeds p0 at usable rates); strain_rate: largest strain change of
    a component a step (> 0; sets the inertia number); gain: fraction of the stress error
    the servo closes in a window, in (0, 1]; window: steps between servo updates and
    checks (>= 1); ramp_steps: steps over which a step's targets move (>= 0); max_steps:
    of one step, then `ConvergenceError` (>= window).
    """

    force_tol: float = 1e-3
    stress_tol: float = 2e-3
    damping: float = 0.7
    strain_rate: float = 5e-7
    gain: float = 0.5
    window: int = 20
    ramp_steps: int = 400
    max_steps: int = 200_000

    def __post_init__(self):
        _require(self, "force_tol", lambda a: 0 < a < 1, "in (0, 1)")
        _require(self, "stress_tol", lambda a: 0 < a < 1, "in (0, 1)")
        _require(self, "damping", lambda a: 0 <= a < 1, "in [0, 1)")
        _require(self, "strain_rate", _positive, "> 0")
        _require(self, "gain", lambda a: 0 < a <= 1, "in (0, 1]")
        _require(self, "window", lambda a: isinstance(a, int) and a >= 1, "an integer >= 1")
        _require(self, "ramp_steps", lambda a: isinstance(a, int) and a >= 0, "an integer >= 0")
        _require(self, "max_steps", lambda a: isinstance(a, int) and a >= self.window,
                 "an integer >= window")


class ConvergenceError(DemError, RuntimeError):
    """A quasi-static step did not converge in ``max_steps``; ``info`` holds what it reached
    (restore the committed state to go on)."""

    def __init__(self, message: str, info: dict):
        super().__init__(message)
        self.info = info


class RVE:
    """A periodic cell of grains as a material point (see the module docstring).

    Args:
        sim: a `dem.Simulation` with a `dem.PeriodicCell` (modified in place).
        solver: `QuasiStatic` settings.
    Use `RVE.consolidate` to make one from `Grains` at an isotropic pressure.
    """

    def __init__(self, sim: Simulation, solver: QuasiStatic | None = None):
        if sim.cell is None:
            raise ValueError("RVE: sim must have a PeriodicCell (Simulation(..., cell=...))")
        self.sim, self.dim = sim, sim.p.dim
        self.solver = QuasiStatic() if solver is None else solver
        if not isinstance(self.solver, QuasiStatic):
            raise ValueError(f"RVE.solver must be a QuasiStatic, got {type(self.solver)}")
        self.k = len(COMPONENTS[self.dim])
        self.h_ref = sim.cell.h.copy()
        self.probe_steps = 0
        self._committed = self.state_dict()

    @classmethod
    def consolidate(cls, grains: Grains, p0: float, solver: QuasiStatic | None = None,
                    gas_strain_rate: float = 2e-5, prestress: float = 2.0) -> RVE:
        """A gas of ``grains`` (random sequential addition in a cube/square) squeezed
        isotropically with ``consolidation_friction`` at ``gas_strain_rate`` a step (a
        quarter of it once there is a contact a grain) until it is jammed above
        ``prestress`` x ``p0`` [Pa] (p0 > 0; dim + 1 contacts a grain, 2 dim - 1/2 without
        friction), unloaded to the isotropic stress -p0 I under stress control of every
        component (a small cell is anisotropic: with its shear strains held it would keep
        shear stresses of ~10 % of p0; with another consolidation friction: roughly, then
        again with the grains' own friction). The strain reference is reset
        there and the state committed. (Servoing up to p0 from the loose side instead
        creeps through fragile states that hold p0 only dynamically, for most of a run.)"""
        if not (_positive(p0)):
            raise ValueError(f"RVE.consolidate: p0 must be > 0 Pa, got {p0!r}")
        if not (_positive(prestress) and prestress >= 1):
            raise ValueError(f"RVE.consolidate: prestress must be >= 1, got {prestress!r}")
        side = grains.cell_side()
        x, r = random_packing(np.zeros(grains.dim), np.full(grains.dim, side),
                              0.5 * grains.d_min, 0.5 * grains.d_max, grains.fraction,
                              seed=grains.seed)
        p = Particles.spheres(x, r, grains.density, dim=grains.dim)
        cell = PeriodicCell(np.eye(grains.dim) * side)
        mu = grains.friction if grains.consolidation_friction is None \
            else grains.consolidation_friction
        soft = replace(grains, friction=mu)
        sim = Simulation(p, soft.material(), cell=cell, safety=grains.safety)
        rve = cls(sim, solver)
        w, dim = rve.solver.window, grains.dim
        for _ in range(rve.solver.max_steps // w):  # isotropic squeeze, slower once touching
            rate = gas_strain_rate if rve.coordination() < 1.0 else 0.25 * gas_strain_rate
            rve._advance(to_mandel(-rate * w * np.eye(3), dim), w)
            if -np.trace(rve.stress()) / dim >= prestress * p0 and \
                    rve.coordination() >= (dim + 1 if mu > 0 else 2 * dim - 0.5):
                break  # jammed (a collision's spike has fewer contacts)
        else:
            raise ConvergenceError(f"RVE.consolidate: the gas did not jam at {prestress * p0:g} "
                                   f"Pa in {rve.solver.max_steps} steps", {})
        iso = dict(stress=-p0 * np.eye(3), mask=np.ones((3, 3), bool), ramp=False)
        if soft.friction != grains.friction:  # near p0, then the grains' own friction
            rough = replace(rve.solver, force_tol=min(0.1, 10 * rve.solver.force_tol),
                            stress_tol=min(0.1, 10 * rve.solver.stress_tol))
            RVE(sim, rough).load(**iso)
            state = sim.state_dict()
            grains_now = {k[10:]: v for k, v in state.items() if k.startswith("particles.")}
            sim = Simulation(Particles.from_state_dict(grains_now),
                             grains.material(), cell=PeriodicCell(cell.h[:grains.dim, :grains.dim]),
                             safety=grains.safety, allow_overlap=True)
            sim.load_state(state)
            rve = cls(sim, solver)
        rve.load(**iso)
        rve.h_ref = sim.cell.h.copy()
        rve.commit()
        return rve

    # ------------------------------------------------------------------ measures
    def stress(self) -> np.ndarray:
        """Love-Weber stress (3, 3) [Pa] now (tension positive; `dem.periodic.cell_stress` to
        round-off, summed as `load` sums it)."""
        return _love_weber(self.sim.contact_forces(return_branch=True), self.sim.cell.volume)

    def strain(self) -> np.ndarray:
        """sym(F) - I (3, 3) since the reference cell ``h_ref``."""
        f = self.sim.cell.h @ np.linalg.inv(self.h_ref)
        return 0.5 * (f + f.T) - np.eye(3)

    def solid_fraction(self) -> float:
        p = self.sim.p
        v = (4.0 / 3.0 * np.pi * p.radius**3) if self.dim == 3 else np.pi * p.radius**2
        return float(v.sum() / self.sim.cell.volume)

    def coordination(self) -> float:
        """Contacts per grain, 2 m / n."""
        return 2.0 * len(self.sim.contacts()[0]) / self.sim.p.n

    def unbalanced_force_ratio(self, contacts=None) -> float:
        """Mean |net force| of the grains over the mean |contact force| (inf without
        contacts; `dem.unbalanced_force_ratio` is 1 in a cell without gravity).
        contacts: `Simulation.contact_forces` output if at hand."""
        p = self.sim.p
        f = (self.sim.contact_forces() if contacts is None else contacts)[1]
        if len(f) == 0:
            return math.inf
        mean_contact = np.linalg.norm(f, axis=1).mean()
        return float(np.linalg.norm(p.force, axis=1).mean() / mean_contact)

    def affine_stiffness(self, contacts=None) -> np.ndarray:
        """Mandel (k, k) [Pa] of the affine (Voigt) contact stiffness, 1/V sum_c l^2 [(kn - kt)
        n n n n + kt sym(n (x) I (x) n)] over the contacts (l branch length, n its
        direction; prestress left out): an upper bound of the packing's stiffness, for the
        servo. contacts: `Simulation.contact_forces(return_branch=True)` if at hand."""
        sim = self.sim
        pairs, _, b = sim.contact_forces(return_branch=True) if contacts is None else contacts
        if len(pairs) == 0:
            return np.zeros((self.k, self.k))
        mi, mj = sim.p.material[pairs[:, 0]], sim.p.material[pairs[:, 1]]
        kn, kt = sim.table[mi, mj, P_KN], sim.table[mi, mj, P_KT]
        ll = np.einsum("ci,ci->c", b, b)
        n = b / np.sqrt(ll)[:, None]
        c4 = np.einsum("c,ci,cj,ck,cl->ijkl", ll * (kn - kt), n, n, n, n)
        c4 += np.einsum("c,ci,cl,jk->ijkl", ll * kt, n, n, np.eye(3))
        c4 = 0.25 * (c4 + c4.transpose(1, 0, 2, 3) + c4.transpose(0, 1, 3, 2)
                     + c4.transpose(1, 0, 3, 2)) / sim.cell.volume
        comps = COMPONENTS[self.dim]
        w = np.array([1.0 if i == j else SQ2 for i, j in comps])
        m = np.array([[c4[i, j, k, q] for k, q in comps] for i, j in comps])
        return m * np.outer(w, w)

    # ------------------------------------------------------------------ loading
    def _sym(self, name, a):
        if a is None:
            return np.zeros((3, 3))
        a = np.asarray(a, float)
        d = self.dim
        if a.shape not in ((3, 3), (d, d)) or not np.isfinite(a).all():
            raise ValueError(f"RVE.load: {name} must be a finite (3, 3) or ({d}, {d}) array, "
                             f"got shape {a.shape}")
        a3 = np.zeros((3, 3))
        a3[: a.shape[0], : a.shape[1]] = a
        if np.abs(a3 - a3.T).max() > 1e-12 * max(np.abs(a3).max(), 1e-300):
            raise ValueError(f"RVE.load: {name} must be symmetric")
        return a3

    def _mask(self, mask):
        if mask is None:
            return np.zeros(self.k, bool)
        m = np.asarray(mask)
        if m.shape not in ((3, 3), (self.dim, self.dim)) or (m != m.T).any():
            raise ValueError(f"RVE.load: mask must be a symmetric bool (3, 3) or "
                             f"({self.dim}, {self.dim}) array, got shape {m.shape}")
        return np.array([bool(m[i, j]) for i, j in COMPONENTS[self.dim]])

    def _advance(self, d, w):
        """Run w damped steps at the velocity gradient that moves the strain by Mandel d."""
        sim, p = self.sim, self.sim.p
        sim.cell.velocity_gradient[:] = from_mandel(d / (w * sim.dt), self.dim)
        a_dt = self.solver.damping * sim.dt
        for _ in range(w):
            _local_damping(p.v, p.omega, p.force, p.torque, p.mass, p.inertia, p.kind, a_dt)
            sim.step(1)
        sim.cell.velocity_gradient[:] = 0.0

    def load(self, strain_increment=None, stress=None, mask=None, *, ramp: bool = True,
             strain_rate: float | None = None) -> dict:
        """One quasi-static step under mixed control.

        Args:
            strain_increment: (3, 3) symmetric strain increment of the components not in
                ``mask`` (None: 0).
            stress: (3, 3) symmetric stress [Pa] that the components in ``mask`` reach.
            mask: (3, 3) symmetric bool, True where the stress is prescribed (None: none,
                pure strain control).
            ramp: move the targets linearly over the ramp (else the stress targets jump).
            strain_rate: cap a step for this call (None: the solver's).
        Returns:
            dict: steps, unbalanced-force ``ratio``, ``stress_error`` (largest, [Pa]) and the
            stress (3, 3) [Pa] reached. Raises `ConvergenceError` after ``max_steps``.
        """
        s, dim, k = self.solver, self.dim, self.k
        m = self._mask(mask)
        de = to_mandel(self._sym("strain_increment", strain_increment), dim)
        if m.any() and stress is None:
            raise ValueError("RVE.load: a mask needs the stress to reach")
        s1 = to_mandel(self._sym("stress", stress), dim)
        rate = s.strain_rate if strain_rate is None else float(strain_rate)
        if not rate > 0:
            raise ValueError(f"RVE.load: strain_rate must be > 0, got {strain_rate!r}")
        w = s.window
        need = math.ceil(np.abs(de[~m]).max(initial=0.0) / rate)
        n_ramp = max(s.ramp_steps if ramp else 0, need)
        n_ramp = w * math.ceil(n_ramp / w)
        s0 = to_mandel(self.stress(), dim)
        normal = [a for a, (i, j) in enumerate(COMPONENTS[dim]) if i == j]
        steps, info = 0, {}
        gain, e_prev = np.full(int(m.sum()), s.gain), None
        while True:
            cf = self.sim.contact_forces(return_branch=True)
            sig_t = _love_weber(cf, self.sim.cell.volume)
            sig = to_mandel(sig_t, dim)
            scale = max(abs(np.mean(sig[normal])), abs(np.mean(s1[normal])) if m.any() else 0.0)
            err = float(np.abs(s1 - sig)[m].max(initial=0.0))
            info = dict(steps=steps, ratio=self.unbalanced_force_ratio(cf), stress_error=err)
            if steps >= n_ramp and info["ratio"] < s.force_tol and err <= s.stress_tol * scale:
                return dict(info, stress=sig_t)
            if steps >= s.max_steps:
                raise ConvergenceError(
                    f"RVE.load: no convergence in {steps} steps (unbalanced-force ratio "
                    f"{info['ratio']:.3g} for {s.force_tol:g}, stress error {err:.4g} Pa for "
                    f"{s.stress_tol * scale:.4g} Pa)", info)
            d = np.zeros(k)
            if steps < n_ramp:
                d[~m] = de[~m] * w / n_ramp
            if m.any():
                f = min(1.0, (steps + w) / n_ramp) if (ramp and n_ramp) else 1.0
                target = s0 + f * (s1 - s0)
                c = self.affine_stiffness(cf)
                css = c[np.ix_(m, m)] + 1e-6 * max(scale, 1.0) * np.eye(int(m.sum()))
                e = (target - sig)[m]
                gain = _adapt(gain, e, e_prev)
                e_prev = e
                dm = gain * np.linalg.solve(css, e - c[np.ix_(m, ~m)] @ d[~m])
                d[m] = dm / max(1.0, np.abs(dm).max() / (rate * w))
            self._advance(d, w)
            steps += w

    def strain_step(self, strain_increment) -> np.ndarray:
        """Pure strain control: apply the (3, 3) increment, relax, return the stress [Pa]."""
        return self.load(strain_increment=strain_increment)["stress"]

    def tangent(self, delta: float = 1e-6, central: bool = False) -> np.ndarray:
        """Mandel (k, k) [Pa] tangent by finite perturbation: column b is (sigma(eps + delta
        e_b) - sigma(eps)) / delta after relaxation under pure strain control (or the central
        difference of +-delta), from the state now, which is restored afterwards (bit for
        bit). A granular packing is incrementally nonlinear: this is the tangent of the
        directions probed, at the strain size delta. ``probe_steps`` is then the DEM steps
        its relaxations took (the state's step count is restored with it)."""
        if not (_positive(delta) and delta < 1e-2):
            raise ValueError(f"RVE.tangent: delta must be in (0, 1e-2), got {delta!r}")
        base = self.state_dict()
        s0 = to_mandel(self.stress(), self.dim)
        t = np.zeros((self.k, self.k))
        self.probe_steps = 0
        try:
            for b in range(self.k):
                for sign in (1.0, -1.0) if central else (1.0,):
                    e = np.zeros(self.k)
                    e[b] = sign * delta
                    info = self.load(strain_increment=from_mandel(e, self.dim))
                    self.probe_steps += info["steps"]
                    s1 = to_mandel(info["stress"], self.dim)
                    ref = s0 if not central else 0.0
                    t[:, b] += sign * (s1 - ref) / (delta * (2.0 if central else 1.0))
                    self.load_state(base)
        finally:
            self.load_state(base)
        return t

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The Simulation's `state_dict` plus ``rve.h_ref`` (3, 3) (copies)."""
        d = self.sim.state_dict()
        d["rve.h_ref"] = self.h_ref.copy()
        return d

    def load_state(self, d) -> None:
        """Restore a `state_dict` (ValueError naming a missing or misfit entry)."""
        d = dict(d)
        if "rve.h_ref" not in d:
            raise ValueError("state has no 'rve.h_ref' (not an RVE state_dict?)")
        h_ref = np.array(d.pop("rve.h_ref"), float)
        if h_ref.shape != (3, 3):
            raise ValueError(f"state 'rve.h_ref' has shape {h_ref.shape}, not (3, 3)")
        self.sim.load_state(d)
        self.h_ref = h_ref

    def commit(self) -> None:
        """Keep the state now as the one `restore` returns to."""
        self._committed = self.state_dict()

    def restore(self) -> None:
        """Return to the committed state (bit for bit)."""
        self.load_state(self._committed)
