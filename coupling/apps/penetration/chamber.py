"""Calibration-chamber loading of the grains: a vertical stress on top, and the lateral
boundary conditions of physical chambers (2D).

A calibration chamber holds its sand under a vertical stress applied on top (a rubber
membrane or a plate with a hole for the rod) and, on its sides, either a constant stress
(BC1: a flexible membrane under fluid pressure) or zero lateral strain (BC3: a rigid wall);
the sample is K0-consolidated first, then the boundary condition of the test is switched
on. Here:

- **surcharge**: the top row of grains (the lattice's highest row) carries the vertical
  stress as constant forces ``sigma_v x (width / top grains)`` (`dem.Simulation.
  set_external_force`), the grains above the cone too: a membrane the cone pierces (a
  hole would leave its grains unloaded, squeezed up by the loaded ones around it);
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

__all__ = ["surcharge", "consolidate", "consolidate_window", "withdraw_walls", "side_servos", "apply_loads",
           "smooth_walls", "box_around"]


def surcharge(x: np.ndarray, candidates: np.ndarray, prm, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows and forces (k, 3) [N per m thickness] of the vertical stress on the top row of
    the lattice ``x`` (n, 3) among the FREE rows ``candidates``: the grains within half a
    radius of the highest centre; ``width`` [m] is the loaded
    width the top row spans (the chamber's, or the window's with its band)."""
    ax = VERTICAL[prm.dim]
    top = float(x[:, ax].max())
    rows = candidates[x[candidates, ax] > top - 0.5 * prm.radius]
    n_row = int(np.sum(np.abs(x[:, ax] - top) < 0.5 * prm.radius))   # with the band's ghosts
    f = np.zeros((len(rows), 3))
    f[:, ax] = -prm.vertical_stress * width / max(n_row, 1)
    return rows, f


def consolidate(sim, prm, log=print) -> dict:
    """Dynamic relaxation under the surcharge to ``prm.consolidation_tol`` (the walls or the
    ghosts hold the sides and the bottom). Returns relax's record with the wall time."""
    from dem import relax

    t0 = time.perf_counter()
    # damping near critical for the specimen's slowest mode (a quarter wave over its height,
    # c = sqrt(stiffness / density)): the default 2 % a step overdamps it, and a creeping
    # consolidation takes ten times the steps
    ax = VERTICAL[prm.dim]
    height = float(np.ptp(sim.p.x[sim.p.kind == 0, ax])) + 2 * prm.radius
    wave = np.sqrt(prm.kn / prm.density) if prm.dim == 2 else np.sqrt(prm.youngs_modulus / prm.density)
    damping = 2 * (np.pi * wave / (2 * height))
    info = relax(sim, tol=prm.consolidation_tol, max_steps=prm.consolidation_max_steps,
                 damping=damping)
    info["wall_time"] = time.perf_counter() - t0
    log(f"consolidated {int((sim.p.kind == 0).sum())} grains under {prm.vertical_stress / 1e3:.4g} kPa in "
        f"{info['steps']} steps ({info['wall_time']:.1f} s), unbalanced force ratio {info['ratio']:.2g}")
    return info


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


def consolidate_window(sim, prm, n: int, band: np.ndarray, width: float, log=print) -> None:
    """Consolidate a coupled window with its ghost band (rows ``band``, GHOST) free inside the
    simulation's smooth walls, under the surcharge on the top row of the ``n`` grains
    spanning ``width`` [m]; then hold the band again (at rest: the ghosts), withdraw the
    walls and keep the surcharge on the window's free top grains only."""
    from dem import FREE, GHOST

    p = sim.p
    p.kind[band] = FREE
    sim.kinds_changed()
    grains = np.arange(n)
    apply_loads(sim, surcharge(p.x[:n], grains, prm, width))
    consolidate(sim, prm, log)
    sim.set_external_force(None, None)
    p.kind[band] = GHOST
    p.v[band] = 0.0
    p.omega[band] = 0.0
    sim.kinds_changed()
    # what the walls carried the ghosts, held where the walls left them, carry now
    withdraw_walls(sim, list(range(len(sim.walls))))
    free = grains[p.kind[:n] == FREE]
    apply_loads(sim, surcharge(p.x[:n], free, prm, width))
