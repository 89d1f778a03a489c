"""Contact laws, one module each, registered in one table (STYLE.md rule 4).

A law is a small pure ``@njit(cache=True)`` function with the common signature of
`dem.contact.linear.linear_force`; it is picked by the integer id ``LAWS[name]`` inside
the one cached pair loop of `dem.forces`. Adding a law = a module + one line in ``LAWS``
+ one branch in `dem.forces.apply_law`. Coefficients are validated here, once, at set-up.

Per-pair parameter rows (``pair_table``) hold, at the indices ``P_*`` below: the law id,
E* and G* [Pa] (LIGGGHTS/LAMMPS mixing, same as peers' ``params.eff``), beta(e), static
and dynamic friction, kn and kt [N/m] (linear law), rolling friction, force clipping flag.

Contact history (per contact, `dem.neighbours.NeighbourList.hist` and ``whist``): ``HIST``
columns, the tangential spring (0:3) [m], then at ``H_FN`` the total normal force [N], at
``H_VN`` the normal approach speed [m/s] and at ``H_CLAIM`` the release claim [steps] of the
last force pass (the dashpot's prediction, `dem.contact.damping`); all zero for a contact
that was open at the last pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dem.errors import MaterialError

__all__ = ["HIST", "LAWS", "ContactMaterial", "beta_of_restitution", "pair_table"]

LAWS = {"linear": 0, "hertz_mindlin": 1}
P_LAW, P_ESTAR, P_GSTAR, P_BETA, P_MUS, P_MUD, P_KN, P_KT, P_MUR, P_CLIP = range(10)
NPARAM = 10
H_FN, H_VN, H_CLAIM = 3, 4, 5
HIST = 6


def beta_of_restitution(e: float) -> float:
    """LIGGGHTS/Tsuji damping parameter beta = ln e / sqrt(ln^2 e + pi^2) (<= 0)."""
    if e >= 1.0:
        return 0.0
    le = math.log(e)
    return le / math.sqrt(le * le + math.pi**2)


@dataclass(frozen=True)
class ContactMaterial:
    """Contact material (SI units), validated on construction.

    E [Pa] > 0, nu in (-1, 0.5), density [kg/m^3] > 0, friction (static) >= 0,
    friction_dynamic in [0, friction] (None: = friction), restitution in (0, 1],
    rolling_friction >= 0 (dimensionless, torque = mu_r F_n R*), law 'hertz_mindlin' or
    'linear'; kn, kt [N/m] required for 'linear' (kn > 0, kt >= 0). ``limit_force``
    clips the total normal force at >= 0 (LIGGGHTS ``limitForce on``).
    """

    E: float
    nu: float
    density: float
    friction: float
    restitution: float
    rolling_friction: float = 0.0
    law: str = "hertz_mindlin"
    kn: float | None = None
    kt: float | None = None
    friction_dynamic: float | None = None
    limit_force: bool = False

    def __post_init__(self):
        def need(name, ok, rng):
            val = getattr(self, name)
            if not ok(val):
                raise MaterialError(f"ContactMaterial.{name} must be {rng}, got {val!r}")

        fin = math.isfinite
        need("E", lambda a: fin(a) and a > 0, "> 0 Pa")
        need("nu", lambda a: -1.0 < a < 0.5, "in (-1, 0.5)")
        need("density", lambda a: fin(a) and a > 0, "> 0 kg/m^3")
        need("friction", lambda a: fin(a) and a >= 0, ">= 0")
        need("restitution", lambda a: 0.0 < a <= 1.0, "in (0, 1]")
        need("rolling_friction", lambda a: fin(a) and a >= 0, ">= 0")
        need("law", lambda a: a in LAWS, f"one of {sorted(LAWS)}")
        if self.friction_dynamic is not None:
            need("friction_dynamic", lambda a: 0 <= a <= self.friction, "in [0, friction]")
        if self.law == "linear":
            need("kn", lambda a: a is not None and fin(a) and a > 0, "> 0 N/m for law 'linear'")
            need("kt", lambda a: a is not None and fin(a) and a >= 0,
                 ">= 0 N/m for law 'linear'")

    @property
    def mu_dynamic(self) -> float:
        return self.friction if self.friction_dynamic is None else self.friction_dynamic


def _pair_row(a: ContactMaterial, b: ContactMaterial, rigid: bool = False) -> np.ndarray:
    """Parameters of material a against material b, or (rigid) against a rigid body with
    b's surface (restitution and friction): the limits of the mixing rules as b's
    compliance vanishes."""
    row = np.zeros(NPARAM)
    row[P_LAW] = LAWS[a.law]
    cb = 0.0 if rigid else 1.0
    row[P_ESTAR] = 1.0 / ((1 - a.nu**2) / a.E + cb * (1 - b.nu**2) / b.E)
    row[P_GSTAR] = 1.0 / (2 * (2 - a.nu) * (1 + a.nu) / a.E
                          + cb * 2 * (2 - b.nu) * (1 + b.nu) / b.E)
    row[P_BETA] = beta_of_restitution(0.5 * (a.restitution + b.restitution))
    row[P_MUS] = min(a.friction, b.friction)
    row[P_MUD] = min(a.mu_dynamic, b.mu_dynamic)
    if a.law == "linear" and rigid:
        row[P_KN], row[P_KT] = 2 * a.kn, 2 * a.kt
    elif a.law == "linear":
        row[P_KN] = 2 * a.kn * b.kn / (a.kn + b.kn)
        row[P_KT] = 0.0 if a.kt * b.kt == 0 else 2 * a.kt * b.kt / (a.kt + b.kt)
    row[P_MUR] = min(a.rolling_friction, b.rolling_friction)
    row[P_CLIP] = float(a.limit_force or b.limit_force)
    return row


def pair_table(materials) -> np.ndarray:
    """(nmat, 2 nmat, NPARAM) table of pair parameters; all materials must share one law.
    Entry [a, b] (b < nmat): material a against material b (a particle or a
    `dem.walls.PlaneWall` of material b); [a, nmat + b]: a against a rigid wall of
    material b (``PlaneWall(rigid=True)``).

    Mixing: E* = 1/((1-nu_a^2)/E_a + (1-nu_b^2)/E_b), G* = 1/(2(2-nu_a)(1+nu_a)/E_a + ...),
    mean restitution, smaller friction, harmonic-mean kn, kt (2 kn_a kn_b/(kn_a + kn_b):
    kn_a for one material). Against a rigid body b's compliance drops out: E* =
    E_a/(1-nu_a^2), G* = E_a/(2(2-nu_a)(1+nu_a)), kn = 2 kn_a, kt = 2 kt_a (twice the
    stiffness of a wall of the particle's own material); restitution and friction mix as
    above."""
    mats = list(materials)
    if not mats:
        raise MaterialError("at least one ContactMaterial is needed")
    if len({m.law for m in mats}) != 1:
        raise MaterialError(f"all materials must use the same law, got {[m.law for m in mats]}")
    n = len(mats)
    t = np.zeros((n, 2 * n, NPARAM))
    for i, a in enumerate(mats):
        for j, b in enumerate(mats):
            t[i, j] = _pair_row(a, b)
            t[i, n + j] = _pair_row(a, b, rigid=True)
    return t
