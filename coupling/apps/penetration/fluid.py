"""Parameters of the pore fluid of a saturated penetration, stated once: defaults, units and
validation (the scene's ``[fluid]`` table names each field ``fluid.<field>``). The run
itself is :mod:`coupling.apps.penetration.saturated`; this module imports no dolfinx, so a
scene is read and checked without it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

__all__ = ["BIOT_3D", "CONTINUA", "FluidParameters"]

#: how the continuum takes the pore pressure (:attr:`FluidParameters.continuum`)
CONTINUA = ("biot", "drained")
#: why a 3D saturated penetration keeps the dry continuum (the scene's and the run's error)
BIOT_3D = ("fluid.continuum = 'biot' is 2D so far: in 3D its P1 pressure increment rang at the chamber's "
           "fixed side wall and grew (scenes/cptu_3d.toml: 2 to 82 kPa in 40 FE steps, then the run blew "
           "up); use fluid.continuum = 'drained'")


@dataclass(frozen=True)
class FluidParameters:
    """A Darcy pore fluid through the window's grains and the chamber (SI units).

    Attributes:
        permeability: intrinsic permeability k [m^2] > 0 of the soil, constant (the
            window's elements hold a few grains each: a Kozeny-Carman k ~ n^3 of their
            porosity would be noise); the penetrator's solid cuts it to a thousandth.
        viscosity: dynamic viscosity mu_f [Pa s] > 0 (water: 1e-3).
        compressibility: beta_f [1/Pa] >= 0 (water: 4.5e-10). A coupled run may take an
            artificial one (e.g. 1e-6) as long as Skempton's ``B = 1 / (1 + n beta_f K)``
            stays near 1 (K the skeleton's bulk modulus): the cell-scale pressure then does
            not drain within a fluid step, and the implicit drag, which resists every change
            of a cell's mean grain velocity (also the isochoric flow round a cone, where the
            fluid goes along), stays small.
        density: rho_f [kg/m^3] >= 0: the free grains' buoyancy ``-rho_f V g``.
        saturation_time: DEM time [s] >= 0 the settled window is given to take the buoyancy
            (ghosts and penetrator held, the fluid drained at the surface) before the push.
        every: DEM steps per fluid step (dividing the FE step's substeps). 1: the fluid's
            forces held over a DEM step, its drag implicit in the next. More: each DEM step
            between takes the last fluid step's response to the grains' displacement since
            it (`coupling.apps.penetration.saturated.ChamberFlow.interval_forces`); held
            forces alone blew up at 5 in the loose window (k = 1e-11, beta_f = 1e-6).
            scenes/cptu_2d.toml takes 25: at V ~ 1 (3 packings, benchmarks/cptu_cost.py)
            q_c 1.4 % below every DEM step's on average (-11 to +5 % a packing), u2 alike,
            at 2.9x the dry push's CPU against 22x (2.5x since, 2.1x with response_every
            5); 50: q_c 11 % below at 2.3x (since: +6 % at 2.1x, -5 % at 1.7x with
            response_every 5, within the packings' scatter).
        response_every: with every > 1, the most DEM steps per application of the
            interval's forces: the impulse of multiple time stepping, s times the middle
            step's force once per block of s steps (`dem.response.LinearResponse`'s stride;
            the 2-rank hook likewise). The run takes the largest divisor s of every up to
            it with ``s dt omega <= 0.5``, omega the interval response's stiffest frequency
            measured at the push's first fluid step (stable below 2; at 0.5 that mode's
            period is 1.1 % short). 1: every DEM step. scenes/cptu_2d.toml takes 5: at
            V ~ 1 omega dt = 0.057, so 5 (benchmarks/cptu_cost.py, 3 packings: push 2.1x
            the dry one's CPU against 2.5x; q_c 4.49 against 4.33 kPa, 4.13 with the fluid
            every DEM step, a packing's scatter ~15 %); undrained omega dt = 0.12, so 1.
            Measured once: over the 45 mm push omega dt stays within 0.056-0.063 at V ~ 1
            and 0.119-0.153 undrained (sampled every 60 FE steps; a one-off probe), well
            inside the margin.
        continuum: how the continuum takes the pore pressure. ``"biot"`` (default): beyond
            the overlap in total stress, its FE step holding the pressure's increment over
            the step with its own flow (`granfe.models.undrained_split.UndrainedSplit`), so
            it stiffens where the fluid cannot drain; in the overlap drained. ``"drained"``:
            the dry continuum everywhere (its pressure only the fixed-stress estimate from
            its volume change), kept to compare. "biot" needs compressibility > 0 (the
            undrained stiffness 1 / (n beta_f)) and the implicit micropolar continuum.
    """

    permeability: float = 1e-12
    viscosity: float = 1e-3
    compressibility: float = 4.5e-10
    density: float = 1000.0
    saturation_time: float = 0.05
    every: int = 1
    continuum: str = "biot"
    response_every: int = 1

    def __post_init__(self):
        if self.continuum not in CONTINUA:
            raise ValueError(f"continuum must be one of {', '.join(map(repr, CONTINUA))}, got "
                             f"{self.continuum!r}")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ValueError(f"every must be an integer >= 1 (DEM steps per fluid step), got "
                             f"{self.every!r}")
        if isinstance(self.response_every, bool) or not isinstance(self.response_every, int) \
                or self.response_every < 1:
            raise ValueError(f"response_every must be an integer >= 1 (DEM steps per application of "
                             f"the interval's forces), got {self.response_every!r}")
        if self.every > 1 and self.every % self.response_every:
            raise ValueError(f"response_every = {self.response_every} must divide every = {self.every} "
                             "(DEM steps per fluid step): a block of steps may not straddle a fluid step")
        for f in fields(self):
            if f.name == "continuum":
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
                raise ValueError(f"{f.name} must be a finite number, got {v!r}")
        for name in ("permeability", "viscosity"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("compressibility", "density", "saturation_time"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.continuum == "biot" and self.compressibility == 0:
            raise ValueError("compressibility must be > 0 with continuum = 'biot' (the continuum's "
                             "undrained stiffness 1 / (n beta_f); an artificial one keeps Skempton's "
                             "B ~ 1), or continuum = 'drained'")

    def consolidation_coefficient(self, modulus: float) -> float:
        """c_v = k M / mu_f [m^2/s] for a skeleton of constrained modulus M [Pa]."""
        return self.permeability * modulus / self.viscosity
