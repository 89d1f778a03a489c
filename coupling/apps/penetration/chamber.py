"""Calibration-chamber loading of the grains: a vertical stress on top, and the lateral
boundary conditions of physical chambers (2D, and 3D under BC3).

A calibration chamber holds its sand under a vertical stress applied on top (a rubber
membrane or a plate with a hole for the rod) and, on its sides, either a constant stress
(BC1: a flexible membrane under fluid pressure) or zero lateral strain (BC3: a rigid wall);
the sample is K0-consolidated first, then the boundary condition of the test is switched
on. Here:

- **surcharge** (2D): the top row of grains (the lattice's highest row) carries the vertical
  stress as constant forces ``sigma_v x (width / top grains)`` (`dem.Simulation.
  set_external_force`), the grains above the cone too: a membrane the cone pierces (a
  hole would leave its grains unloaded, squeezed up by the loaded ones around it);
- **top plate** (3D): a smooth rigid plate on the top grains, servo-controlled at the vertical
  stress (`dem.ServoWall`) while consolidating and during the push, as the top wall of DEM
  chambers (Arroyo et al. 2011); only FREE grains touch it (``free_only``): the cone passes
  through. Its equilibrium is measured by PFC's ratio of the mean unbalanced force to the
  mean contact force (`dem.control.mean_force_ratio`): loaded through walls, every grain's
  contact resultant is unbalanced force. The Hertz spheres need the default step (0.2 of
  the Rayleigh step, ``dt_factor = 1``) at these stresses: at 50 kPa with E = 29 MPa the
  contacts are 6 % of a radius deep and stiffer than the Rayleigh estimate assumes, and at
  0.3 of it the packing heated up instead of settling (ratio 0.5 after 200k steps; 2750
  steps to 1e-2 at 0.2).
- **consolidation**: dynamic relaxation (`dem.relax`) to a stated unbalanced-force ratio,
  with the sides rigid and smooth (frictionless walls: rough ones carry the load by
  friction, as in a silo): K0. A coupled window consolidates with its ghost band as one
  specimen inside smooth walls round the band, and the band's grains are held (become the
  ghosts) only then: a band held from the start would carry the surcharge by friction (a
  window 20 grains wide measured 39 kPa of vertical stress under 100 kPa on top);
- **BC1**: the side walls are then servo-controlled (`dem.ServoWall`, updated once per
  block of DEM steps) to hold the lateral stress they carried at the end of consolidation,
  as DEM calibration chambers do (Arroyo et al. 2011); BC3 keeps them fixed. (Constant
  forces on the boundary grains instead, a point-load membrane, leaked: the grains between
  the loaded ones squeezed out and the chamber spread.)

The continuum side of a coupled chamber carries the increment from this state (see
:mod:`coupling.apps.penetration.coupled`): its top is traction-free (the vertical stress
stays constant), its sides on rollers (BC3) or traction-free (BC1).
"""

from __future__ import annotations

import time

import numpy as np

from coupling.apps.penetration.parameters import VERTICAL

__all__ = ["surcharge", "packing_modulus", "consolidate", "top_plate", "plate_servo", "consolidate_window",
           "withdraw_walls", "side_servos", "apply_loads", "smooth_walls", "box_around"]


def surcharge(x: np.ndarray, candidates: np.ndarray, prm, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows and forces (k, 3) [N; per m thickness in 2D] of the vertical stress on the top
    row of the lattice ``x`` (n, 3) among the FREE rows ``candidates``: the grains within half
    a radius of the highest centre; ``width`` [m] is the loaded width the top row spans (the
    chamber's, or the window's with its band; the side of a square in 3D)."""
    ax = VERTICAL[prm.dim]
    top = float(x[:, ax].max())
    rows = candidates[x[candidates, ax] > top - 0.5 * prm.radius]
    n_row = int(np.sum(np.abs(x[:, ax] - top) < 0.5 * prm.radius))   # with the band's ghosts
    f = np.zeros((len(rows), 3))
    f[:, ax] = -prm.vertical_stress * width ** (prm.dim - 1) / max(n_row, 1)
    return rows, f


def packing_modulus(prm) -> float:
    """The order of the packing's modulus [Pa] under the vertical stress: ``kn`` for the 2D
    linear disks (N/m per m thickness), ``(E*^2 sigma_v)^(1/3)`` for Hertz spheres (their
    contact stiffness grows as the cube root of the force; Walton 1987's scaling, E* = E / (2
    (1 - nu^2))): at 50 kPa 1/30 of E, whose wave speed overdamps the consolidation 3x."""
    if prm.dim == 2:
        return prm.kn
    e_star = prm.youngs_modulus / (2 * (1 - prm.nu**2))
    return float((e_star**2 * max(prm.vertical_stress, prm.density * prm.gravity * prm.radius)) ** (1 / 3))


def consolidate(sim, prm, log=print, controllers=(), height: float | None = None,
                grains: int | None = None, ratio=None) -> dict:
    """Dynamic relaxation under the surcharge (or the servo-controlled top plate among
    ``controllers``) to ``prm.consolidation_tol`` (the walls or the ghosts hold the sides and
    the bottom). ``height`` [m] of the specimen and its number of ``grains`` (for the log)
    default to the FREE particles' extent plus a diameter and their count (a `dem.
    DistributedSimulation`, whose particles no single rank holds, is given them). Returns
    relax's record with the wall time. ``ratio``: the measure of equilibrium (`dem.relax`;
    default PFC's mean-force ratio with controllers, else the unbalanced-force ratio)."""
    from dem import relax

    t0 = time.perf_counter()
    # damping near critical for the specimen's slowest mode (a quarter wave over its height,
    # c = sqrt(stiffness / density)): the default 2 % a step overdamps it, and a creeping
    # consolidation takes ten times the steps
    ax = VERTICAL[prm.dim]
    if height is None:
        height = float(np.ptp(sim.p.x[sim.p.kind == 0, ax])) + 2 * prm.radius
    if grains is None:
        grains = int((sim.p.kind == 0).sum())
    wave = np.sqrt(packing_modulus(prm) / prm.density)
    damping = 2 * (np.pi * wave / (2 * height))
    # a packing loaded through a plate: every contact resultant is unbalanced force until the
    # end, PFC's ratio of the means measures its equilibrium
    from dem.control import mean_force_ratio, unbalanced_force_ratio

    info = relax(sim, tol=prm.consolidation_tol, max_steps=prm.consolidation_max_steps,
                 damping=damping, controllers=controllers,
                 ratio=ratio or (mean_force_ratio if controllers else unbalanced_force_ratio))
    info["wall_time"] = time.perf_counter() - t0
    log(f"consolidated {grains} grains under {prm.vertical_stress / 1e3:.4g} kPa in "
        f"{info['steps']} steps ({info['wall_time']:.1f} s), unbalanced force ratio {info['ratio']:.2g}")
    return info


def top_plate(x: np.ndarray, radius: np.ndarray, dim: int):
    """The loading plate (3D): a smooth wall (material 1) on the highest grain's top, facing
    down, touched by FREE grains only (the penetrator passes through it)."""
    from dem import PlaneWall

    ax = VERTICAL[dim]
    e = np.eye(3)[ax]
    return PlaneWall(tuple(float((x[:, ax] + radius).max()) * e), tuple(-e), material=1, free_only=True)


def plate_servo(prm, wall: int, area: float):
    """`dem.ServoWall` holding the top plate ``wall`` at ``prm.vertical_stress`` over ``area``
    [m^2]. Its speed is a fifth of the particle velocity of a stress wave of the error's
    amplitude in the packing, ``0.2 (sigma_v - sigma) / (rho c)`` (a plate moving at the
    full particle velocity would make the error's stress; ``rho`` the bulk density at a solid
    fraction of 0.6, ``c`` the wave speed of :func:`packing_modulus`): a gain set by the
    packing's impedance, stable whether the servo acts every step or once a block."""
    from dem import ServoWall

    rho = 0.6 * prm.density
    impedance = rho * np.sqrt(packing_modulus(prm) / rho)
    return ServoWall(wall, prm.vertical_stress, area, 0.2 / impedance, max(prm.velocity, 0.1))


def withdraw_walls(sim, walls: list[int]) -> None:
    """Move the planar walls ``walls`` far outward along their normals (their contacts end;
    the contact history of the rest is kept)."""
    span = float(np.ptp(sim.p.x, axis=0).max()) + 1.0
    for k in walls:
        sim.walls.point[k] -= span * sim.walls.normal[k]
    sim.compute_forces()


def side_servos(sim, walls: list[int], height: float, width: float, modulus: float, block: float,
                velocity: float) -> list:
    """BC1: `dem.ServoWall` controllers holding the side walls ``walls`` at the lateral stress
    they carry now (smooth walls: their normal force over ``height`` [m], per unit thickness
    in 2D), updated every ``block`` [s]. The gain moves a wall, over one block, by a fifth of
    what would cancel the stress error in a chamber of ``width`` [m] and constrained modulus
    ``modulus`` [Pa] (more overshoots); speed at most the push ``velocity`` [m/s]."""
    from dem import ServoWall

    sim.compute_forces(update_history=False)
    gain = 0.2 * width / (modulus * block)
    return [ServoWall(k, float(-(sim.walls.force[k] @ sim.walls.normal[k]) / height), height, gain, velocity)
            for k in walls]


def apply_loads(sim, *loads) -> None:
    """Set the sum of several (rows, forces) loads as the simulation's external forces (a
    grain may carry several)."""
    rows = np.concatenate([r for r, _ in loads]) if loads else np.zeros(0, np.int64)
    f = np.concatenate([f for _, f in loads]) if loads else np.zeros((0, 3))
    uniq, inv = np.unique(rows, return_inverse=True)
    total = np.zeros((len(uniq), 3))
    np.add.at(total, inv, f)
    sim.set_external_force(uniq, total)


def smooth_walls(material) -> list:
    """The grains' material and a frictionless twin for walls (material 1; the pair takes
    the smaller friction)."""
    from dataclasses import replace

    return [material, replace(material, friction=0.0)]


def box_width(x: np.ndarray, radius: np.ndarray, dim: int) -> float:
    """The loaded width [m] between the side walls of :func:`box_around` (3D: the side of the
    square of the same area): what a stress on the top of the lattice ``x`` acts over. The
    lattice's own extent is a diameter less, which servo-controlled a 3D window's plate to
    91 % of the vertical stress (2.5 cm window)."""
    r = float(radius.max())
    spans = [float(x[:, k].max() - x[:, k].min()) + 2 * r for k in range(dim - 1)]
    return float(np.prod(spans) ** (1.0 / (dim - 1)))


def box_around(x: np.ndarray, radius: np.ndarray, dim: int) -> list:
    """Smooth walls (material 1) touching the lattice ``x`` (n, 3) on its sides and bottom."""
    from dem import PlaneWall

    ax = VERTICAL[dim]
    r = float(radius.max())
    walls = []
    for k in range(dim - 1):
        e = np.eye(3)[k]
        walls.append(PlaneWall(tuple((x[:, k].min() - r) * e), tuple(e), material=1))
        walls.append(PlaneWall(tuple((x[:, k].max() + r) * e), tuple(-e), material=1))
    e = np.eye(3)[ax]
    walls.append(PlaneWall(tuple((x[:, ax].min() - r) * e), tuple(e), material=1))
    return walls


def consolidate_window(sim, prm, n: int, band: np.ndarray, width: float, log=print,
                       plate: int | None = None):
    """Consolidate a coupled window with its ghost band (rows ``band``, GHOST) free inside the
    simulation's smooth walls, under the surcharge on the top row of the ``n`` grains
    spanning ``width`` [m] (or the top plate, wall ``plate``, servo-controlled); then hold
    the band again (at rest: the ghosts), withdraw the walls (the plate stays) and keep the
    surcharge on the window's free top grains only. Returns the plate's servo for the push
    (None without a plate): the force the free grains put on the plate now, held."""
    from dem import FREE, GHOST

    p = sim.p
    p.kind[band] = FREE
    sim.kinds_changed()
    grains = np.arange(n)
    if plate is None:
        apply_loads(sim, surcharge(p.x[:n], grains, prm, width))
        consolidate(sim, prm, log)
        sim.set_external_force(None, None)
    else:
        consolidate(sim, prm, log, controllers=[plate_servo(prm, plate, width ** (prm.dim - 1))])
    p.kind[band] = GHOST
    p.v[band] = 0.0
    p.omega[band] = 0.0
    sim.kinds_changed()
    # what the walls carried the ghosts, held where the walls left them, carry now
    withdraw_walls(sim, [k for k in range(len(sim.walls)) if k != plate])
    if plate is None:
        free = grains[p.kind[:n] == FREE]
        apply_loads(sim, surcharge(p.x[:n], free, prm, width))
        return None
    # the plate now rests on the free grains alone: it keeps their share of the load
    sim.compute_forces(update_history=False)
    carried = float(-(sim.walls.force[plate] @ sim.walls.normal[plate]))
    return plate_servo(prm, plate, carried / prm.vertical_stress)
