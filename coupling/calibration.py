"""Continuum constants of the grains from virtual element tests on periodic DEM cells.

A periodic cell (:class:`dem.periodic.PeriodicCell`: prescribed velocity gradient L, the
Love-Weber cell stress) of the scene's grains is prepared at the stress level p and put
through element tests whose responses give the constants of the micropolar continuum and
of its Drucker-Prager cone (matched to Mohr-Coulomb, :mod:`granfe.models.drucker_prager`):

1. preparation: grains (``"random"``: polydisperse, random sequential addition; or the
   scenes' ``"lattice"``: hexagonal disks / fcc spheres, radii reduced by up to a spread)
   compressed isotropically without friction to p (a dense packing), friction switched on,
   settled;
2. isotropic compression: the bulk modulus ``K = dp / de_v`` (2D, plane strain:
   ``K = lam + G``; 3D: ``K = lam + 2 G / 3``);
3. simple shear ``u_x = g y``, grains free to rotate: ``G = d sigma_xy / d g`` (symmetric part);
4. simple shear with the grains' spins held: the skew stress against the relative rotation
   of grains and continuum, ``kappa = d (sigma_xy - sigma_yx) / d g`` (the micropolar strain
   ``grad u + e phi`` has the skew part g / 2 at phi = 0);
5. oedometric compression (uniaxial strain along y): ``M = lam + 2 G``, a consistency check;
6. simple shear at constant normal stress to large strain: the mobilised friction angle
   ``sin phi = (s1 - s3) / -(s1 + s3)`` (principal stresses, tension positive) at its peak
   and at the critical state (mean over the last third), and the dilatancy angle at the
   peak, ``sin psi = e_v' / sqrt(e_v'^2 + g'^2)`` (rates of the volumetric and shear strain).

Tests 2-5 are central differences of ``+-increment`` from the same settled state (restored
with ``state_dict`` / ``load_state``), each settled after its strain is applied. Stresses use
the continuum's index convention (``t_i = sigma_ij n_j``; the cell stress's transpose).
``gamma`` is not measured (a homogeneous cell has no curvature): it is ``2 G l^2`` with the
length ``l`` taken from the grain size.

Beside the measured constants the estimates used today are reported: in 2D the bonded
hexagonal lattice (:func:`dem.bonded.hexagonal_lattice_micropolar`, stiffnesses scaled by the
coordination number over 6, rolling stiffness ``0.1 kt d^2``), in 3D the affine (Voigt)
estimate of ``coupling/apps/penetration/coupled.py``. This module imports both ``dem`` and
``granfe`` (for the materials it returns); run ``python -m coupling.calibration --help``.
"""

from __future__ import annotations

import argparse
import json
import math
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numba
import numpy as np

from dem import ContactMaterial, Particles, Simulation
from dem.bonded import hexagonal_lattice_micropolar
from dem.contact import P_ESTAR, P_GSTAR, pair_table
from dem.packing import random_packing
from dem.periodic import PeriodicCell, cell_stress

__all__ = ["CellTest", "Calibration", "calibrate", "lattice_estimate", "voigt_estimate", "main"]

PACKINGS = ("random", "lattice")


@dataclass(frozen=True)
class CellTest:
    """The grains, the cell and the stress level of a calibration.

    Attributes:
        material: the grains' contact law (its friction acts in the tests; the packing is
            compressed without it).
        radius: mean grain radius [m].
        dim: 2 (disks of unit thickness, plane strain) or 3 (spheres).
        pressure: mean stress p [Pa] of the tests (compression positive).
        grains: number of grains (the lattice rounds it).
        packing: ``"random"`` (radii uniform in ``radius (1 +- spread)``) or ``"lattice"``
            (hexagonal / fcc of ``radius``, radii reduced by up to ``spread``, as the scenes).
        spread: of the radii (see packing), in [0, 0.5).
        seed: of the packing.
        increment: strain of the elastic tests (small: no contact may slide nor open); None:
            the strain that changes p by 1 % in the affine estimate of the bulk modulus.
        shear_strain: final shear strain of test 6 (0: no strength test).
        inertial_number: shear rate of test 6, ``I = g' d / sqrt(p / rho)`` (quasi-static < 1e-2).
        length_over_diameter: Cosserat length l over the mean grain diameter.
        settle_tolerance: a state is settled when the mean net force on a grain is below this
            fraction of the mean contact force.
    """

    material: ContactMaterial
    radius: float
    dim: int = 2
    pressure: float = 2e3
    grains: int = 200
    packing: str = "random"
    spread: float = 0.2
    seed: int = 0
    increment: float | None = None
    shear_strain: float = 0.4
    inertial_number: float = 3e-3
    length_over_diameter: float = 1.0
    settle_tolerance: float = 1e-3

    def __post_init__(self):
        checks = (
            ("material", isinstance(self.material, ContactMaterial), "a dem.ContactMaterial"),
            ("radius", self.radius > 0, "> 0 m"), ("dim", self.dim in (2, 3), "2 or 3"),
            ("pressure", self.pressure > 0, "> 0 Pa"), ("grains", self.grains >= 8, ">= 8"),
            ("packing", self.packing in PACKINGS, f"one of {PACKINGS}"),
            ("spread", 0 <= self.spread < 0.5, "in [0, 0.5)"),
            ("increment", self.increment is None or 0 < self.increment < 1e-2, "None or in (0, 1e-2)"),
            ("shear_strain", 0 <= self.shear_strain <= 2, "in [0, 2]"),
            ("inertial_number", 0 < self.inertial_number <= 0.1, "in (0, 0.1]"),
            ("length_over_diameter", self.length_over_diameter > 0, "> 0"),
            ("settle_tolerance", 0 < self.settle_tolerance < 1, "in (0, 1)"),
        )
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"CellTest.{name} must be {rule}, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class Calibration:
    """Constants measured on a periodic cell, with the test curves and today's estimate.

    Attributes:
        test: the :class:`CellTest`.
        lam, mu, kappa: micropolar constants [Pa] (Eringen's; ``G = mu + kappa / 2``).
        gamma: ``2 G l^2`` [N] (2D: per unit thickness), from the length.
        length: ``l`` [m].
        bulk_modulus, shear_modulus, oedometric_modulus: K, G, M [Pa] as measured (K in the
            plane in 2D).
        friction_peak_deg, friction_critical_deg, dilatancy_deg: Mohr-Coulomb angles of the
            strength test (None without it).
        grains: the number in the cell.
        solid_fraction, coordination: of the settled cell at p.
        density: of the packing [kg/m^3] (grain density times solid fraction).
        estimate: today's estimate (name, lam, mu, kappa, gamma [Pa, N]).
        curves: per test, lists of the measured quantities (SI, strains dimensionless).
    """

    test: CellTest
    lam: float
    mu: float
    kappa: float
    gamma: float
    length: float
    bulk_modulus: float
    shear_modulus: float
    oedometric_modulus: float
    friction_peak_deg: float | None
    friction_critical_deg: float | None
    dilatancy_deg: float | None
    grains: int
    solid_fraction: float
    coordination: float
    density: float
    estimate: dict = field(default_factory=dict)
    curves: dict = field(default_factory=dict)

    def micropolar(self):
        """The :class:`granfe.materials.MicropolarMaterial` (``j`` of the grains' spin:
        ``r^2 / 2`` disks, ``0.4 r^2`` spheres, as the penetration scenes)."""
        from granfe.materials import MicropolarMaterial

        j = (0.5 if self.test.dim == 2 else 0.4) * self.test.radius**2
        return MicropolarMaterial(lam=self.lam, mu=self.mu, kappa=self.kappa, gamma=self.gamma,
                                  rho=self.density, j=j)

    def drucker_prager(self, match: str | None = None, state: str = "peak"):
        """A cohesionless :class:`granfe.models.drucker_prager.DruckerPragerMaterial` with the
        peak (or ``"critical"``: no dilatancy) angles; match default: plane strain in 2D,
        triaxial compression in 3D."""
        from granfe.models.drucker_prager import DruckerPragerMaterial

        if self.friction_peak_deg is None:
            raise ValueError("this calibration has no strength test (shear_strain = 0)")
        if state not in ("peak", "critical"):
            raise ValueError(f"state must be 'peak' or 'critical', got {state!r}")
        phi = self.friction_peak_deg if state == "peak" else self.friction_critical_deg
        psi = min(max(self.dilatancy_deg, 0.0), phi) if state == "peak" else 0.0
        match = match or ("plane_strain" if self.test.dim == 2 else "triaxial_compression")
        return DruckerPragerMaterial(self.micropolar(), 0.0, phi, psi, match=match)

    def to_dict(self) -> dict:
        """JSON-ready: the constants, the inputs (the contact law as a dict) and the curves."""
        d = asdict(self)
        d["test"]["material"] = asdict(self.test.material)
        return d


# ---- the cell ---------------------------------------------------------------------------
def _lattice(test: CellTest) -> tuple[np.ndarray, np.ndarray]:
    """Periodic hexagonal (2D) or fcc (3D) sites of spacing 2 radius: centres (n, 3) and the
    cell vectors (dim, dim)."""
    a = 2 * test.radius
    if test.dim == 2:
        nx = max(2, round(math.sqrt(test.grains)))
        ny = 2 * max(1, round(test.grains / nx / 2))          # even: periodic rows
        j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        x = np.column_stack([((i + 0.5 * (j % 2)) * a).ravel(), (j * a * math.sqrt(3) / 2).ravel(),
                             np.zeros(i.size)])
        return x + 0.25 * a * np.array([1, 1, 0]), np.diag([nx * a, ny * a * math.sqrt(3) / 2])
    n = max(2, round((test.grains / 4) ** (1 / 3)))
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 1, 3)
    edge = a * math.sqrt(2)
    return ((g + base).reshape(-1, 3) + 0.25) * edge, np.eye(3) * n * edge


def _grains(test: CellTest) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (n, 3), radii (n,) and cell vectors (dim, dim) of the loose starting cell."""
    rng = np.random.default_rng(test.seed)
    if test.packing == "lattice":
        x, h0 = _lattice(test)
        return x, test.radius * (1 - test.spread * rng.random(len(x))), h0
    dim, r = test.dim, test.radius
    fraction = 0.5 if dim == 2 else 0.3            # below the random-addition jamming
    volume = test.grains * (math.pi * r**2 if dim == 2 else 4 / 3 * math.pi * r**3) / fraction
    side = volume ** (1 / dim)
    x, radius = random_packing(np.zeros(dim), np.full(dim, side), r * (1 - test.spread),
                               r * (1 + test.spread), fraction, seed=test.seed, strict=False)
    return x, radius, np.eye(dim) * side


def _simulation(test: CellTest) -> Simulation:
    x, radius, h0 = _grains(test)
    density = test.material.density
    frictionless = replace(test.material, friction=0.0, friction_dynamic=None)
    p = Particles.spheres(x, radius, density, dim=test.dim)
    # 0.2 of the critical step: a quasi-static test needs stability, not energy accuracy
    return Simulation(p, frictionless, cell=PeriodicCell(h0), safety=0.2, allow_overlap=True)


def _set_friction(sim: Simulation, material: ContactMaterial) -> None:
    sim.materials, sim.table = [material], pair_table([material])


def stress(sim: Simulation) -> np.ndarray:
    """Cell stress (dim, dim) [Pa] in the continuum's convention (``t_i = sigma_ij n_j``)."""
    d = sim.p.dim
    return cell_stress(sim, symmetric=False)[:d, :d].T.copy()


def pressure(sim: Simulation) -> float:
    """Mean stress p [Pa], compression positive (2D: of the in-plane stresses)."""
    return float(-np.trace(stress(sim)) / sim.p.dim)


def _residual(sim: Simulation) -> float:
    """Mean net force on a grain over the mean contact force (0 in equilibrium)."""
    _, f = sim.contact_forces()
    if len(f) == 0:
        return 0.0          # nothing to balance: a loose cell at rest
    return float(np.linalg.norm(sim.p.force, axis=1).mean() / np.linalg.norm(f, axis=1).mean())


def settle(sim: Simulation, tolerance: float, max_steps: int = 100_000, strict: bool = True) -> int:
    """Relax the cell (L = 0) by kinetic damping: every 10 steps, if the kinetic energy fell
    since the last look (it peaked in between), the grains are stopped (the cell's state,
    not its dynamics, is what a test measures; unlike viscous damping this does not slow the
    soft modes of a loose packing down). Returns the steps; raises RuntimeError naming the
    residual reached (``strict``) or returns after ``max_steps`` anyway."""
    sim.cell.velocity_gradient[:] = 0.0
    steps, res, last = 0, math.inf, math.inf
    while steps < max_steps:
        for _ in range(10):
            sim.step(10)
            kinetic = float(sim.kinetic_energy().sum())
            if kinetic < last:
                sim.p.v[:] = 0.0
                sim.p.omega[:] = 0.0
                kinetic = 0.0
            last = kinetic
        steps += 100
        res = _residual(sim)
        if res < tolerance:
            return steps
    if not strict:
        return steps
    raise RuntimeError(f"the cell did not settle to a residual of {tolerance:g} in {max_steps} "
                       f"steps (reached {res:.3g}); loosen settle_tolerance")


def _shear_rate(test: CellTest) -> float:
    return test.inertial_number * math.sqrt(test.pressure / test.material.density) / (2 * test.radius)


def _bulk_estimate(sim: Simulation) -> float:
    """Affine bulk modulus [Pa] of the contact network (``Z phi kn / 2 pi`` for disks,
    ``Z phi kn / 6 pi R`` for spheres); the servo's first guess."""
    st = _packing_state(sim)
    if sim.p.dim == 2:
        return st["coordination"] * st["solid_fraction"] * st["kn"] / (2 * math.pi)
    return st["coordination"] * st["solid_fraction"] * st["kn"] / (6 * math.pi * float(np.mean(sim.p.radius)))


def compress(sim: Simulation, test: CellTest, tolerance: float = 0.02) -> int:
    """Isotropic compression to ``test.pressure`` (within ``tolerance``), settled; returns the
    steps. Fast while the grains are loose; then strain steps from the secant bulk modulus,
    each at most at the quasi-static rate and settled."""
    d, rate, target, steps = test.dim, _shear_rate(test), test.pressure, 0
    p, fast = pressure(sim), 10.0
    for _ in range(100):            # until the settled packing carries load
        while (p := pressure(sim)) < target:
            sim.cell.velocity_gradient[:d, :d] = -rate * (fast if p < 0.05 * target else 1) * np.eye(d)
            sim.step(20)
            steps += 20
        fast = 1.0                  # near jamming the dynamic pressure of a fast push misleads
        steps += settle(sim, test.settle_tolerance, max_steps=20_000, strict=False)
        if (p := pressure(sim)) > 0.5 * target:
            break
    bulk = _bulk_estimate(sim)
    for _ in range(40):
        if abs(p - target) < tolerance * target:
            return steps
        strain = (p - target) / bulk / d            # per axis, compression negative
        n = max(20, math.ceil(abs(strain) / (rate * sim.dt)))
        sim.cell.velocity_gradient[:d, :d] = strain / (n * sim.dt) * np.eye(d)
        sim.step(n)
        steps += n + settle(sim, test.settle_tolerance)
        p_new = pressure(sim)
        secant = (p_new - p) / (-d * strain)
        bulk = secant if secant > 0.05 * bulk else bulk / 2   # rearranging packings soften
        p = p_new
    raise RuntimeError(f"isotropic compression did not settle at p = {target} Pa "
                       f"(reached {p:.4g} Pa)")


# ---- the tests --------------------------------------------------------------------------
def _dir(d, i, j, v):
    m = np.zeros((d, d))
    m[i, j] = v
    return m


# elastic tests: the velocity gradient's direction (compression for +), whether the grains'
# spins are held, the strain and the stress measures whose ratio is the modulus
ELASTIC = {
    "isotropic": (lambda d: -np.eye(d), False, np.trace, lambda s: np.trace(s) / len(s)),
    "shear": (lambda d: _dir(d, 0, 1, 1.0), False, lambda e: e[0, 1], lambda s: (s[0, 1] + s[1, 0]) / 2),
    "shear_spins_held": (lambda d: _dir(d, 0, 1, 1.0), True, lambda e: e[0, 1],
                         lambda s: s[0, 1] - s[1, 0]),
    "oedometric": (lambda d: _dir(d, 1, 1, -1.0), False, lambda e: e[1, 1], lambda s: s[1, 1]),
}


def _strained(sim: Simulation, ref: dict, velocity_gradient: np.ndarray, test: CellTest,
              hold_spins: bool) -> tuple[np.ndarray, np.ndarray]:
    """From the state ``ref``: apply the velocity gradient for 50 steps, settle; the
    displacement gradient since ``ref`` and the stress (dim, dim)."""
    d = test.dim
    sim.load_state(ref)
    h_ref = sim.cell.h[:d, :d].copy()
    inertia = sim.p.inertia.copy()
    if hold_spins:          # rotary inertia 1e12 times the grains': they keep omega = 0
        sim.p.inertia *= 1e12
        sim.p.omega[:] = 0.0
    try:
        sim.cell.velocity_gradient[:d, :d] = velocity_gradient / (50 * sim.dt)
        sim.step(50)
        settle(sim, test.settle_tolerance)
    finally:
        sim.p.inertia[:] = inertia
    return sim.cell.h[:d, :d] @ np.linalg.inv(h_ref) - np.eye(d), stress(sim)


def elastic_test(sim: Simulation, ref: dict, name: str, test: CellTest) -> tuple[float, dict]:
    """The modulus [Pa] of one elastic test by central differences about ``ref``, and its
    curve: strain and stress measures (changes from ``ref``) at -increment, 0, +increment."""
    direction, hold, strain_of, stress_of = ELASTIC[name]
    sim.load_state(ref)
    s0 = stress_of(stress(sim))
    increment = test.increment or 0.01 * test.pressure / _bulk_estimate(sim)
    ends = [_strained(sim, ref, sign * increment * direction(test.dim), test, hold)
            for sign in (-1, 1)]
    e = [float(strain_of(g)) for g, _ in ends]
    s = [float(stress_of(t) - s0) for _, t in ends]
    return (s[1] - s[0]) / (e[1] - e[0]), {"strain": [e[0], 0.0, e[1]], "stress": [s[0], 0.0, s[1]]}


def shear_test(sim: Simulation, ref: dict, test: CellTest) -> dict:
    """Simple shear at the constant normal stress -p (a servo on L_yy) from ``ref`` to
    ``test.shear_strain``; the curves every 20 steps: shear strain g, volumetric strain
    (log), normal stress, shear stress, sin of the mobilised friction angle."""
    d, rate, target = test.dim, _shear_rate(test), test.pressure
    sim.load_state(ref)
    h_ref = sim.cell.h.copy()
    curve = {k: [] for k in ("shear_strain", "volumetric_strain", "normal_stress", "shear_stress",
                             "sin_friction")}
    g = 0.0
    while g < test.shear_strain:
        s = stress(sim)
        sim.cell.velocity_gradient[:] = 0.0
        sim.cell.velocity_gradient[0, 1] = rate
        # normal stress held: expand when the grains push harder than p, compress when less;
        # the gain of 10 leaves 1.5 % of p as the lag of a P-control when dilating at 0.15 g'
        sim.cell.velocity_gradient[1, 1] = float(np.clip(10 * rate * (-s[1, 1] - target) / target,
                                                         -rate, rate))
        sim.step(20)
        F = sim.cell.h @ np.linalg.inv(h_ref)
        g = float(F[0, 1] / F[1, 1])
        sym = 0.5 * (s + s.T)
        lo, hi = np.linalg.eigvalsh(sym)[[0, -1]]
        for k, v in zip(curve, (g, math.log(np.linalg.det(F[:d, :d])), -s[1, 1], sym[0, 1],
                                (hi - lo) / -(lo + hi)), strict=True):
            curve[k].append(float(v))
    return curve


def strength(curve: dict, window: float = 0.02) -> tuple[float, float, float]:
    """Peak and critical-state friction angles and the dilatancy angle at the peak [deg] of a
    shear curve: the peak of the mobilised friction smoothed over ``window`` of shear strain,
    the mean over the last third, the slope of the volumetric strain over +-window."""
    g, ev = np.array(curve["shear_strain"]), np.array(curve["volumetric_strain"])
    sin_phi = np.array(curve["sin_friction"])
    k = max(1, int(round(window / max(np.diff(g).mean(), 1e-12))))
    smooth = np.convolve(sin_phi, np.ones(k) / k, mode="same")
    inner = slice(k // 2, len(g) - k // 2)
    peak = int(np.argmax(smooth[inner])) + inner.start
    critical = float(sin_phi[g >= g[-1] * 2 / 3].mean())
    near = np.abs(g - g[peak]) <= window
    rate = np.polyfit(g[near], ev[near], 1)[0]                       # e_v' / g'
    psi = math.degrees(math.asin(rate / math.sqrt(1 + rate**2)))
    return (math.degrees(math.asin(smooth[peak])), math.degrees(math.asin(critical)), psi)


# ---- today's estimates ------------------------------------------------------------------
def _packing_state(sim: Simulation) -> dict:
    """Coordination number, solid fraction and the mean tangent contact stiffnesses."""
    p, d = sim.p, sim.p.dim
    pairs, _, branch = sim.contact_forces(return_branch=True)
    measure = np.pi * p.radius**2 if d == 2 else 4 / 3 * np.pi * p.radius**3
    mat = sim.materials[0]
    if mat.law == "linear":
        kn, kt = mat.kn, mat.kt
    else:                   # Hertz-Mindlin tangents at the mean contact radius
        ri, rj = p.radius[pairs[:, 0]], p.radius[pairs[:, 1]]
        a = np.sqrt(ri * rj / (ri + rj) * (ri + rj - np.linalg.norm(branch, axis=1)))
        row = pair_table([mat])[0, 0]
        kn, kt = float(np.mean(2 * row[P_ESTAR] * a)), float(np.mean(8 * row[P_GSTAR] * a))
    return {"coordination": 2 * len(pairs) / p.n, "solid_fraction": float(measure.sum() / sim.cell.volume),
            "kn": float(kn), "kt": float(kt)}


def lattice_estimate(state: dict, radius: float) -> dict:
    """2D, as the penetration scenes: the bonded hexagonal lattice's constants with kn, kt
    scaled by Z / 6 and the rolling stiffness ``0.1 kt d^2``."""
    s = state["coordination"] / 6
    kt = s * state["kt"]
    c = hexagonal_lattice_micropolar(s * state["kn"], kt, 0.1 * kt * (2 * radius) ** 2)
    return {"name": "bonded hexagonal lattice, Z / 6", **{k: float(v) for k, v in c.items()}}


def voigt_estimate(state: dict, radius: float) -> dict:
    """3D, as the penetration scenes: the affine (Voigt) estimate of an isotropic packing
    (``A = 3 phi Z / (2 pi R)``, ``lam = mu = A (kn - kt) / 15``, ``kappa = A kt / 3``,
    ``gamma = A kr / 3``, ``kr = 0.1 kt d^2``)."""
    A = 3 * state["solid_fraction"] * state["coordination"] / (2 * math.pi * radius)
    kn, kt = state["kn"], state["kt"]
    return {"name": "affine (Voigt)", "lam": A * (kn - kt) / 15, "mu": A * (kn - kt) / 15,
            "kappa": A * kt / 3, "gamma": A * 0.1 * kt * (2 * radius) ** 2 / 3}


# ---- the calibration --------------------------------------------------------------------
def prepare(test: CellTest) -> Simulation:
    """The settled frictional cell at ``test.pressure``."""
    sim = _simulation(test)
    compress(sim, test)
    _set_friction(sim, test.material)
    settle(sim, test.settle_tolerance)
    return sim


@contextmanager
def _one_thread():
    """A cell of a few hundred grains runs on one numba thread: a parallel region's rendezvous
    costs more than it saves there (7x slower with 2 threads on 2 busy cores)."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(threads)


def calibrate(test: CellTest) -> Calibration:
    """Run the element tests of the module docstring on a cell of ``test``'s grains."""
    with _one_thread():
        return _calibrate(test)


def _calibrate(test: CellTest) -> Calibration:
    sim = prepare(test)
    ref = sim.state_dict()
    state = _packing_state(sim)
    moduli, curves = {}, {}
    for name in ELASTIC:
        moduli[name], curves[name] = elastic_test(sim, ref, name, test)
    K, G, kappa, M = (moduli[k] for k in ("isotropic", "shear", "shear_spins_held", "oedometric"))
    lam = K - G if test.dim == 2 else K - 2 * G / 3
    angles = (None, None, None)
    if test.shear_strain > 0:
        curves["shear_to_failure"] = shear_test(sim, ref, test)
        angles = strength(curves["shear_to_failure"])
    length = test.length_over_diameter * 2 * float(np.mean(sim.p.radius))
    estimate = (lattice_estimate if test.dim == 2 else voigt_estimate)(state, test.radius)
    return Calibration(test=test, lam=lam, mu=G - kappa / 2, kappa=kappa, gamma=2 * G * length**2,
                       length=length, bulk_modulus=K, shear_modulus=G, oedometric_modulus=M,
                       friction_peak_deg=angles[0], friction_critical_deg=angles[1],
                       dilatancy_deg=angles[2], grains=sim.p.n, solid_fraction=state["solid_fraction"],
                       coordination=state["coordination"],
                       density=test.material.density * state["solid_fraction"],
                       estimate={**estimate, "kn": state["kn"], "kt": state["kt"]}, curves=curves)


# ---- the continuum on the same path -----------------------------------------------------
def continuum_shear(cal: Calibration, match: str = "plane_strain", steps: int = 200) -> dict:
    """The calibrated Drucker-Prager continuum (:meth:`Calibration.drucker_prager`) through
    test 6 at a material point: isotropic p, then simple shear with ``e_xx = 0`` and the
    normal stress held at -p (the volumetric strain found by secant iterations), the
    micro-rotation following the macro-rotation (no couple stress, no skew stress). The test
    is plane strain in 3D too (``e_zz = 0``), hence the plane-strain match by default (the
    triaxial one overestimates a plane-strain strength: phi = 35 deg becomes ~60). The
    model's UFL stresses are evaluated on a one-cell mesh; returns the curve in the keys of
    :func:`shear_test`."""
    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI

    from dolfinx import fem, mesh

    from granfe.models.drucker_prager import MicropolarDruckerPrager
    from granfe.problem import ContinuumProblem

    d, target = cal.test.dim, cal.test.pressure
    material = cal.drucker_prager(match)
    cell = (mesh.create_unit_square(MPI.COMM_SELF, 1, 1, mesh.CellType.quadrilateral) if d == 2
            else mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, mesh.CellType.hexahedron))
    problem = ContinuumProblem(cell, MicropolarDruckerPrager(material), degree=(1, 1),
                               quadrature_degree=1, prefix="calibration_point_")
    sigma = fem.Expression(problem.stresses()["sigma"], np.zeros((1, d)) + 0.5)
    e0 = -target / (d * cal.bulk_modulus)          # isotropic p from the stress-free state

    def stress_at(g, e):
        u = problem.w.sub(0)
        u.interpolate(lambda x: np.vstack([e0 * x[0] + g * x[1], (e0 + e) * x[1]]
                                          + [e0 * x[2]] * (d == 3)))
        rot = problem.w.sub(1)
        rot.interpolate(lambda x: np.full(x.shape[1], -g / 2) if d == 2
                        else np.vstack([0 * x[0], 0 * x[0], np.full(x.shape[1], -g / 2)]))
        problem.w.x.scatter_forward()
        return sigma.eval(cell, np.array([0], dtype=np.int32)).reshape(d, d)

    curve = {k: [] for k in ("shear_strain", "volumetric_strain", "normal_stress", "shear_stress",
                             "sin_friction")}
    e = 0.0
    for g in np.linspace(0, cal.test.shear_strain, steps + 1)[1:]:
        e = _secant(lambda v, g=g: stress_at(g, v)[1, 1] + target, e, 0.01 * target / cal.bulk_modulus)
        s = stress_at(g, e)
        problem.state.commit()
        sym = 0.5 * (s + s.T)
        lo, hi = np.linalg.eigvalsh(sym)[[0, -1]]
        for k, v in zip(curve, (g, math.log1p(e), -s[1, 1], sym[0, 1], (hi - lo) / -(lo + hi)),
                        strict=True):
            curve[k].append(float(v))
    return curve


def _secant(f, x0: float, dx: float, tol: float = 1e-10, its: int = 50) -> float:
    """A root of the scalar, monotone f near x0 (secant steps from x0 and x0 + dx)."""
    x1, f0 = x0 + dx, f(x0)
    for _ in range(its):
        f1 = f(x1)
        if abs(f1) <= tol * max(1.0, abs(f0)) or f1 == f0:
            return x1
        x0, x1, f0 = x1, x1 - f1 * (x1 - x0) / (f1 - f0), f1
    raise RuntimeError(f"no root of the normal stress condition near {x0:.4g}")


# ---- command line -----------------------------------------------------------------------
def _grains_of_scene(path: Path) -> dict:
    """The [grains] table and dimension of a scene TOML (read as data, no application)."""
    import tomllib

    scene = tomllib.loads(path.read_text())
    return {"dim": int(scene.get("scene", {}).get("dimension", 2)), **scene.get("grains", {})}


def _material(g: dict, dim: int) -> ContactMaterial:
    common = dict(nu=g.get("nu", 0.25), density=g.get("density", 2650.0),
                  friction=g.get("friction", 0.5), restitution=g.get("restitution", 0.5))
    if dim == 2:             # linear disks of unit thickness, as the 2D scenes
        kn = g.get("kn", 2e5)
        return ContactMaterial(E=kn, law="linear", kn=kn, kt=g.get("kt_over_kn", 0.5) * kn, **common)
    return ContactMaterial(E=g.get("youngs_modulus", 2.9e7), law="hertz_mindlin", **common)


def plot(cal: Calibration, model: dict | None, path: Path) -> None:
    """The elastic tests with their fitted moduli, and the strength test against the model."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for name, c in cal.curves.items():
        if name != "shear_to_failure":
            axes[0].plot(1e3 * np.array(c["strain"]), np.array(c["stress"]) / 1e3, "o-", label=name)
    axes[0].set_xlabel("strain measure [1e-3]")
    axes[0].set_ylabel("stress measure change [kPa]")
    axes[0].legend(fontsize=8)
    shear = cal.curves.get("shear_to_failure")
    for curve, style, label in ((shear, "-", "DEM cell"), (model, "--", "calibrated continuum")):
        if curve:
            g = np.array(curve["shear_strain"])
            axes[1].plot(g, np.degrees(np.arcsin(curve["sin_friction"])), style, label=label)
            axes[2].plot(g, curve["volumetric_strain"], style, label=label)
    if shear:
        for v, ls in ((cal.friction_peak_deg, ":"), (cal.friction_critical_deg, "-.")):
            axes[1].axhline(v, ls=ls, color="0.5")
    axes[1].set_xlabel("shear strain")
    axes[1].set_ylabel("mobilised friction angle [deg]")
    axes[2].set_xlabel("shear strain")
    axes[2].set_ylabel("volumetric strain")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.suptitle(f"{cal.test.dim}D {cal.test.packing} cell, {cal.grains} grains, "
                 f"p = {cal.test.pressure:g} Pa", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> dict:
    """``python -m coupling.calibration [--scene scenes/cpt_2d.toml] --pressure P --out DIR``:
    calibrate, write ``calibration.json`` and ``calibration.png``; returns the JSON dict."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", type=Path, help="take the grains from this scene's [grains]")
    parser.add_argument("--dim", type=int, choices=(2, 3), help="(default: the scene's, else 2)")
    parser.add_argument("--radius", type=float, help="mean grain radius [m] (default: the scene's)")
    parser.add_argument("--pressure", type=float, default=2e3, help="stress level p [Pa]")
    parser.add_argument("--grains", type=int, default=200)
    parser.add_argument("--packing", choices=PACKINGS, default="random")
    parser.add_argument("--spread", type=float, default=0.2)
    parser.add_argument("--shear-strain", type=float, default=0.4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("output/calibration"))
    args = parser.parse_args(argv)
    g = _grains_of_scene(args.scene) if args.scene else {}
    dim = args.dim or g.get("dim", 2)
    test = CellTest(_material(g, dim), args.radius or g.get("radius", 1.5e-3), dim=dim,
                    pressure=args.pressure, grains=args.grains, packing=args.packing,
                    spread=args.spread, seed=args.seed, shear_strain=args.shear_strain)
    cal = calibrate(test)
    model = continuum_shear(cal) if test.shear_strain > 0 else None
    out = cal.to_dict()
    out["continuum_shear"] = model
    if model:
        peak = math.degrees(math.asin(min(max(model["sin_friction"]), 1.0)))
        out["continuum_peak_friction_deg"] = peak
        out["continuum_peak_error"] = peak / cal.friction_peak_deg - 1
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "calibration.json").write_text(json.dumps(out, indent=1))
    plot(cal, model, args.out / "calibration.png")
    print(f"K {cal.bulk_modulus:.4g} G {cal.shear_modulus:.4g} kappa {cal.kappa:.4g} Pa; lam "
          f"{cal.lam:.4g} mu {cal.mu:.4g}; today's {cal.estimate['name']}: lam "
          f"{cal.estimate['lam']:.4g} mu {cal.estimate['mu']:.4g} kappa {cal.estimate['kappa']:.4g}; "
          f"phi peak {cal.friction_peak_deg}, critical {cal.friction_critical_deg}, psi "
          f"{cal.dilatancy_deg} deg; written to {args.out}")
    return out


if __name__ == "__main__":
    main()
