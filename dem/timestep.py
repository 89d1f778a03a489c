"""Critical time step estimates and the time step choice.

- Rayleigh: dt_R = pi r sqrt(rho/G) / (0.1631 nu + 0.8766), G = E/(2(1+nu)), minimum over
  particles (the usual Hertz-Mindlin choice; peers run at 0.2 dt_R).
- Hertz: stability of the linearised contact at the largest overlap reached at the
  approach speed v_max: dt = 2 sqrt(m*/k), k = dF/d delta = 2 E* sqrt(R* delta_max),
  delta_max = (15 m* v^2 / (16 E* sqrt(R*)))^(2/5).
- Linear: dt = 2 sqrt(m*/kn) for two equal particles of the smallest mass.
"""

from __future__ import annotations

import math

import numpy as np

from dem.contact import ContactMaterial
from dem.errors import TimeStepError

__all__ = ["DEFAULT_SAFETY", "choose_dt", "critical_dt", "default_time_step", "hertz_dt", "rayleigh_dt"]


def rayleigh_dt(radius, E: float, nu: float, density: float) -> float:
    """Rayleigh step [s] for the smallest radius [m]."""
    G = E / (2.0 * (1.0 + nu))
    return math.pi * float(np.min(radius)) * math.sqrt(density / G) / (0.1631 * nu + 0.8766)


def hertz_dt(material: ContactMaterial, radius: float, mass: float, v_max: float) -> float:
    """Hertz stability estimate [s] for two equal particles (radius [m], mass [kg]) meeting
    at v_max [m/s]."""
    es = 1.0 / (2.0 * (1.0 - material.nu**2) / material.E)
    rs, ms = 0.5 * radius, 0.5 * mass
    dmax = (15.0 * ms * v_max**2 / (16.0 * es * math.sqrt(rs))) ** 0.4
    return 2.0 * math.sqrt(ms / (2.0 * es * math.sqrt(rs * dmax)))


def critical_dt(particles, materials, v_max: float | None = None) -> float:
    """Smallest critical step [s] over the materials in use (Rayleigh for Hertz-Mindlin,
    plus the Hertz estimate when v_max [m/s] is given; 2 sqrt(m*/kn) for linear)."""
    dts = []
    for k, mat in enumerate(materials):
        sel = particles.material == k
        if not sel.any():
            continue
        r, m = particles.radius[sel], particles.mass[sel]
        if mat.law == "linear":
            dts.append(2.0 * math.sqrt(0.5 * m.min() / mat.kn))
            continue
        dts.append(rayleigh_dt(r, mat.E, mat.nu, mat.density))
        if v_max is not None and v_max > 0:
            i = int(np.argmin(m))
            dts.append(hertz_dt(mat, float(r[i]), float(m[i]), v_max))
    if not dts:
        raise ValueError("no particle uses any of the given materials")
    return min(dts)


DEFAULT_SAFETY = {"hertz_mindlin": 0.2, "linear": 0.05}
"""Default dt / dt_crit: 0.2 Rayleigh (peers; ~27 steps per Hertz contact) and 0.05 of the
linear stability limit (~31 steps per linear contact)."""


def default_time_step(particles, materials, v_max: float | None = None) -> float:
    """The step [s] a `dem.Simulation` of these particles and materials takes by default
    (``dt=None``): `DEFAULT_SAFETY` of the first material's law times `critical_dt`, known
    before the simulation is built (to size a push velocity or an output interval)."""
    mats = [materials] if isinstance(materials, ContactMaterial) else list(materials)
    return DEFAULT_SAFETY[mats[0].law] * critical_dt(particles, mats, v_max)


def choose_dt(dt: float | None, dt_crit: float, safety: float = 0.2,
              force: bool = False) -> float:
    """``safety * dt_crit`` if dt is None; a user dt above dt_crit raises `TimeStepError`
    unless ``force``."""
    if not 0 < safety <= 1:
        raise ValueError(f"safety must be in (0, 1], got {safety!r}")
    if dt is None:
        return safety * dt_crit
    if not dt > 0:
        raise ValueError(f"dt must be > 0 s, got {dt!r}")
    if dt > dt_crit and not force:
        raise TimeStepError(f"dt = {dt:.4g} s is above the critical step {dt_crit:.4g} s "
                            f"(use dt <= {dt_crit:.4g} s, or force_dt=True to insist)")
    return float(dt)
