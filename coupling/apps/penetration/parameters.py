"""Parameters of a penetration run, stated once: defaults, units and validation.

The scene tables (:mod:`coupling.apps.penetration.scene`) take their defaults from these
fields and name them by ``section.key`` (field metadata), so a default, a range or a message
lives in one place.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem.timestep import DEFAULT_SAFETY

__all__ = ["CONTINUA", "PenetrationParameters", "MovingWindowParameters", "VERTICAL"]

VERTICAL = {2: 1, 3: 2}   # index of the vertical (penetration) axis
# the continuum models a penetration couples to its grains (PenetrationParameters.continuum)
CONTINUA = ("micropolar", "micropolar_drucker_prager", "micromorphic", "micromorphic_drucker_prager")


@dataclass(frozen=True)
class PenetrationParameters:
    """All lengths in m, times in s. Defaults: a 2 cm cone into ~1000 disks of 1.5 mm (2D).

    In 3D (``dim = 3``) ``chamber_width`` is the chamber's diameter (under a
    ``vertical_stress``: the side of its square, the full DEM's box of plane walls), the window is the square
    prism ``|x|, |y| <= window_half_width`` of depth ``window_depth``, the grains are
    Hertz-Mindlin spheres of Young's modulus ``youngs_modulus`` (``kn`` and ``kt_over_kn``
    are 2D only), and ``shape`` is ``"cone"`` (apex ``apex_deg``) or ``"pile"`` (flat end),
    both of radius ``cone_radius``.
    """

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
    kn: float = 2.0e5                 # linear contact stiffness [N/m per m thickness] (2D)
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
    relaxation: float = 0.3           # of the prescribed values D^ (forces: the loads) per FE step
    # "loose": one exchange per FE step, relaxed; "iqn-ils": the exchange iterated within the
    # FE step (DEM rewound each time) to interface_tol, accelerated by interface quasi-Newton;
    # "forces": ghosts from the FE, their reactions back as its loads, nothing of the FE
    # prescribed (coupling.reactions), one exchange per FE step
    interface: str = "loose"
    interface_tol: float = 1e-3       # relative change of the prescribed displacements
    # on more than one rank, the push's grains split over the ranks by space (a
    # dem.DistributedSimulation continuing the consolidated window, which every rank still
    # builds alike); False: every rank runs all of them (3D chambers under a vertical stress)
    distribute_grains: bool = False
    interface_max_iterations: int = 15
    settle_time: float = 0.3
    gravity: float = 9.81
    seed: int = 1
    dim: int = 2
    shape: str = "cone"
    # Hertz-Mindlin spheres (3D): quartz E = 2.9e10 Pa (seed 002 Table 1) scaled by 1e-3, so
    # that the explicit step is ~30x longer; contact stiffness, and q_c with it, scale down
    youngs_modulus: float = 2.9e7
    # stability studies (benchmarks/stability.py): the DEM step times dt_factor (past the
    # critical step above 1 / safety: 20 for the 2D linear law, 5 in 3D) and the continuum's
    # constants times continuum_stiffness (1: consistent with the grains)
    dt_factor: float = 1.0
    continuum_stiffness: float = 1.0
    # calibration-chamber loading (coupling.apps.penetration.chamber): a vertical stress
    # [Pa] on the top grains (0: a free surface under gravity), consolidated by dynamic
    # relaxation to consolidation_tol (unbalanced-force ratio); lateral = "rigid" keeps the
    # sides from moving (BC3, zero lateral strain), "stress" holds the consolidated lateral
    # stress constant (BC1, servo-controlled side walls; 2D)
    vertical_stress: float = 0.0
    lateral: str = "rigid"
    consolidation_tol: float = 1e-3
    consolidation_max_steps: int = 200_000
    # the continuum model (granfe.models): "micropolar" (elastic) or
    # "micropolar_drucker_prager" (chambers under a vertical stress: its initial stress is
    # the consolidated window's mean stress), with the cone matched to Mohr-Coulomb in plane
    # strain (2D) or on the compression meridian (3D)
    continuum: str = "micropolar"
    # where the continuum's constants come from: "lattice", the bonded hexagonal lattice's
    # constants scaled by the settled window's coordination (2D) or the affine estimate of its
    # Hertz-Mindlin contacts (3D); "calibrated", element
    # tests on a periodic cell of the scene's grains at the window's consolidated mean stress
    # (coupling.calibration; with the Drucker-Prager model its peak friction and dilatancy
    # angles replace continuum_friction_deg / continuum_dilatancy_deg); "window" (3D chamber):
    # the affine estimate scaled to the consolidated window's constrained modulus, probed in
    # situ by a tenth more stress on its plate (CoupledPenetration._window_modulus);
    # "window_isotropic": both isotropic constants from that probe (lam from the lateral
    # stress it raises, the shear modulus from the rest), not the affine Poisson ratio
    continuum_constants: str = "lattice"
    continuum_friction_deg: float = 30.0
    continuum_dilatancy_deg: float = 0.0
    continuum_cohesion: float = 0.0
    # linear hardening of the Drucker-Prager cohesion [Pa per unit equivalent plastic strain]:
    # with perfect plasticity the continuum round a displacement-driven window has no tangent
    # stiffness once it yields, and the window drifts with its grains (a 4.5 cm window sank
    # 24 mm and q_c fell to zero); hardening keeps a restoring stiffness
    continuum_hardening: float = 0.0
    # the continuum's time stepping: "implicit" (generalized-alpha, rho_inf 0.8; a plastic
    # model by quasi-Newton on its elastic Jacobian) or "explicit" (granfe.explicit: central
    # differences on a lumped mass, the FE step split into substeps below the measured
    # stability limit; a plastic step is one fused return and force pass per substep, no solve)
    continuum_integrator: str = "implicit"
    # mass-proportional damping alpha [1/s] of the explicit continuum (granfe.explicit): the
    # far field's material damping; an undamped one rings at its fundamental mode
    continuum_damping: float = 0.0
    # continuum = "micromorphic" (u and phi = chi - I; coupling.micro_kinematics): the packing's
    # micropolar constants (lam, mu, kappa, gamma) as the micromorphic energy
    # lam/2 tr(eps)^2 + G |eps|^2 + b/2 |sym(grad u - phi)|^2 + kappa/2 |skew(grad u - phi)|^2
    # + gamma/4 |grad phi|^2 (G = mu + kappa / 2), whose limit b -> inf is the micropolar
    # solid; continuum_micro_stiffness is b / G, how stiffly the micro-stretch follows the
    # grains' strain (CoupledPenetration._micromorphic_material). "micromorphic_drucker_prager":
    # that solid with the Drucker-Prager cone of continuum_friction_deg, _dilatancy_deg,
    # _cohesion and _hardening on its macro stress (the micro and higher-order levels
    # elastic); its moduli couple the levels (sigma = -b), so the three levels return
    # together at the points (granfe.models.micromorphic_iterative). 3D free surface only:
    # the continuum's own geostatic solve gives the total stress its cone needs
    continuum_micro_stiffness: float = 1.0

    def __post_init__(self):
        self._check_values()
        self._check_loading()
        self._check_geometry()

    def _check_values(self):
        """Each value on its own: signs, ranges, choices."""
        for name in ("chamber_width", "chamber_depth", "window_half_width", "window_depth",
                     "ghost_width", "handshake", "element_size_window", "element_size_far",
                     "radius", "kn", "density", "cone_radius", "velocity", "depth", "settle_time",
                     "youngs_modulus", "dt_factor", "continuum_stiffness"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if self.ghost_width < 1.0:
            raise ValueError(f"ghost_width = {self.ghost_width} grain diameters is too thin: the "
                             "ghost band holds the window's grains (>= 1 diameter)")
        for name in ("friction", "kt_over_kn"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must lie in [0, inf), got {v!r}")
        if not (0.0 < self.restitution <= 1.0):
            raise ValueError(f"restitution must lie in (0, 1], got {self.restitution!r}")
        if not (-1.0 < self.nu < 0.5):
            raise ValueError(f"nu must lie in (-1, 0.5), got {self.nu!r}")
        if not np.isfinite(self.gravity):
            raise ValueError(f"gravity must be finite, got {self.gravity!r}")
        if not (isinstance(self.seed, int | np.integer) and self.seed >= 0):
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if not (10.0 <= self.apex_deg <= 180.0):
            raise ValueError(f"apex_deg must lie in [10, 180] degrees, got {self.apex_deg!r}")
        if not 0 < self.relaxation <= 1:
            raise ValueError(f"relaxation must lie in (0, 1], got {self.relaxation!r}")
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim!r}")
        if self.shape not in ("cone", "pile"):
            raise ValueError(f"shape must be 'cone' or 'pile', got {self.shape!r}")
        if not 0 <= self.jitter < 0.5:
            raise ValueError(f"jitter must lie in [0, 0.5), got {self.jitter!r}")
        law = "linear" if self.dim == 2 else "hertz_mindlin"
        if self.dt_factor * DEFAULT_SAFETY[law] > 1.0:
            raise ValueError(f"dt_factor = {self.dt_factor} puts the DEM step above the critical "
                             f"step of the {law} law (the default is {DEFAULT_SAFETY[law]} of it: "
                             f"dt_factor <= {1 / DEFAULT_SAFETY[law]:g})")
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps!r}")
        if self.interface not in ("loose", "iqn-ils", "forces"):
            raise ValueError(f"interface must be 'loose', 'iqn-ils' or 'forces', got {self.interface!r}")
        if not 0 < self.interface_tol < 1:
            raise ValueError(f"interface_tol must lie in (0, 1), got {self.interface_tol!r}")
        if not (isinstance(self.interface_max_iterations, int) and self.interface_max_iterations >= 1):
            raise ValueError(f"interface_max_iterations must be an integer >= 1, "
                             f"got {self.interface_max_iterations!r}")

    def _check_loading(self):
        """The chamber's loading (coupling.apps.penetration.chamber) and the continuum model."""
        if self.continuum_constants.startswith("window") and not (self.dim == 3 and self.vertical_stress > 0):
            raise ValueError(f"continuum_constants = {self.continuum_constants!r} probes the window under "
                             "the 3D chamber's top plate: it needs dim = 3 and vertical_stress > 0")
        if not isinstance(self.distribute_grains, bool):
            raise ValueError(f"distribute_grains must be true or false, got {self.distribute_grains!r}")
        if self.distribute_grains and not (self.dim == 3 and self.vertical_stress > 0):
            raise ValueError("distribute_grains = true splits the 3D chamber's push over the ranks: it "
                             "needs dim = 3 and vertical_stress > 0")
        if self.interface == "forces" and self.dim == 3 and self.vertical_stress == 0:
            raise ValueError("interface = 'forces' needs the increment from a consolidated state "
                             "(2D, or vertical_stress > 0 in 3D): the 3D geostatic start "
                             "prescribes the window's nodes")
        self._check_continuum()
        if self.continuum_constants not in ("lattice", "calibrated", "window", "window_isotropic"):
            raise ValueError(f"continuum_constants must be 'lattice', 'calibrated', 'window' or "
                             f"'window_isotropic', "
                             f"got {self.continuum_constants!r}")
        if not (0 <= self.continuum_friction_deg < 90):
            raise ValueError(f"continuum_friction_deg must lie in [0, 90), got {self.continuum_friction_deg!r}")
        if not (0 <= self.continuum_dilatancy_deg <= self.continuum_friction_deg):
            raise ValueError(f"continuum_dilatancy_deg must lie in [0, continuum_friction_deg], "
                             f"got {self.continuum_dilatancy_deg!r}")
        if not (np.isfinite(self.continuum_cohesion) and self.continuum_cohesion >= 0):
            raise ValueError(f"continuum_cohesion must be >= 0 Pa, got {self.continuum_cohesion!r}")
        if self.continuum_integrator not in ("implicit", "explicit"):
            raise ValueError(f"continuum_integrator must be 'implicit' or 'explicit', "
                             f"got {self.continuum_integrator!r}")
        if not (np.isfinite(self.continuum_damping) and self.continuum_damping >= 0):
            raise ValueError(f"continuum_damping must be >= 0 1/s, got {self.continuum_damping!r}")
        if self.continuum_damping and self.continuum_integrator != "explicit":
            raise ValueError("continuum_damping (mass-proportional) is the explicit continuum's: "
                             f"continuum_integrator = {self.continuum_integrator!r}")
        if not (np.isfinite(self.continuum_hardening) and self.continuum_hardening >= 0):
            raise ValueError(f"continuum_hardening must be >= 0 Pa, got {self.continuum_hardening!r}")
        if not (np.isfinite(self.vertical_stress) and self.vertical_stress >= 0):
            raise ValueError(f"vertical_stress must be >= 0 Pa, got {self.vertical_stress!r}")
        if self.lateral not in ("rigid", "stress"):
            raise ValueError(f"lateral must be 'rigid' (BC3) or 'stress' (BC1), got {self.lateral!r}")
        if self.lateral == "stress" and self.dim != 2:
            raise ValueError("lateral = 'stress' (BC1) needs dim = 2 (the 3D chamber's sides are "
                             "rigid: BC3)")
        if not 0 < self.consolidation_tol < 1:
            raise ValueError(f"consolidation_tol must lie in (0, 1), got {self.consolidation_tol!r}")
        if self.consolidation_max_steps < 1:
            raise ValueError(f"consolidation_max_steps must be >= 1, got {self.consolidation_max_steps!r}")

    def _check_continuum(self):
        """The continuum model against the exchange, the integrator and the loading."""
        if self.continuum not in CONTINUA:
            raise ValueError(f"continuum must be {', '.join(map(repr, CONTINUA[:-1]))} or "
                             f"{CONTINUA[-1]!r}, got {self.continuum!r}")
        if not (np.isfinite(self.continuum_micro_stiffness) and self.continuum_micro_stiffness > 0):
            raise ValueError(f"continuum_micro_stiffness (b / G of the micromorphic continuum) must be "
                             f"> 0, got {self.continuum_micro_stiffness!r}")
        if self.continuum.startswith("micromorphic") and (self.interface != "loose"
                                                          or self.continuum_integrator != "implicit"):
            raise ValueError(f"continuum = {self.continuum!r} couples by the loose exchange with the "
                             f"implicit integrator so far (its phi fitted once per FE step): interface = "
                             f"{self.interface!r} and continuum_integrator = {self.continuum_integrator!r} "
                             f"need interface = 'loose', continuum_integrator = 'implicit'")
        if self.continuum == "micropolar_drucker_prager" and not self.vertical_stress > 0:
            raise ValueError("continuum = 'micropolar_drucker_prager' needs vertical_stress > 0 (its "
                             "yield function needs the total stress: a uniform initial stress, the "
                             "consolidated chamber's; a free surface under gravity has none yet)")
        if self.continuum == "micromorphic_drucker_prager" and not (self.dim == 3 and self.vertical_stress == 0):
            raise ValueError(f"continuum = 'micromorphic_drucker_prager' needs dim = 3 and vertical_stress "
                             f"= 0 (got dim = {self.dim}, vertical_stress = {self.vertical_stress!r}): its "
                             "cone needs the total stress, which the continuum carries only from its own "
                             "geostatic solve under gravity (the 3D free surface); it has no initial stress "
                             "for the increment from a consolidated chamber")
        if (self.continuum == "micromorphic_drucker_prager" and self.continuum_constants != "calibrated"
                and self.continuum_friction_deg == 0 and self.continuum_cohesion == 0):
            raise ValueError("continuum = 'micromorphic_drucker_prager': continuum_friction_deg = 0 with "
                             "continuum_cohesion = 0 has no strength")

    def _check_geometry(self):
        """The sizes against each other: mesh, window, cone, chamber."""
        if self.element_size_window > self.element_size_far:
            raise ValueError(f"element_size_window = {self.element_size_window} is coarser than "
                             f"element_size_far = {self.element_size_far}: the mesh is refined "
                             "toward the window, not away from it")
        if self.element_size_far > min(self.chamber_width, self.chamber_depth):
            raise ValueError(f"element_size_far = {self.element_size_far} is larger than the chamber "
                             f"(chamber_width = {self.chamber_width}, chamber_depth = {self.chamber_depth})")
        if self.shape == "pile" and self.dim == 2:
            raise ValueError("shape = 'pile' needs dim = 3 (the 2D penetrator is a cone's section)")
        if self.window_half_width <= 2 * self.cone_radius:
            raise ValueError(f"window_half_width = {self.window_half_width} must exceed twice the "
                             f"cone radius ({self.cone_radius}): the cone must stay inside the window")
        if self.depth + self.cone_radius * 2 >= self.window_depth:
            raise ValueError(f"depth = {self.depth} m leaves the cone too close to the window base "
                             f"(window_depth = {self.window_depth} m)")
        reach = self.window_half_width + (self.ghost_width + 1) * 2 * self.radius
        if reach * (np.sqrt(2) if self.dim == 3 else 1.0) >= self.chamber_width / 2:
            raise ValueError("the window and its ghost band must lie inside the chamber "
                             f"(chamber_width = {self.chamber_width} m is too small)")



@dataclass(frozen=True)
class MovingWindowParameters:
    """How the DE window follows the tip. Lengths in grain diameters unless stated.

    Attributes:
        depth: total penetration depth [m] (beyond what the initial window allows).
        trigger: the window moves when the tip is this close to its bottom.
        step: how far the bottom moves per move.
        max_height: largest window height [m] (the Box's extent along the axis, whose top
            starts above the free surface); None: the window only grows. A top that would lie
            less than a ghost band below the surface stays where it was.
        settle_steps: DEM steps of settling after a move (ghosts and cone held).
        servo_cycles: the second half of the settle is split into this many parts; before
            each, the radii of the grains being generated are scaled so that their axial
            stress approaches the target (module docstring, 6.); 0: a plain settle.
        servo_rate: largest relative radius change per servo cycle (the grains grow by at
            most ``(1 + servo_rate) ** servo_cycles``).
        settle_hold: free grains closer than this to the cone are held during the settle
            too (the cone is paused: left free they would relax away from the tip and the
            tip force would drop).
        relax_iterations: geometric push-apart iterations for new grains' overlaps.
        overlap_tolerance: overlap left after the push-apart, fraction of the mean radius.
        max_moves: a run stops moving the window after this many moves.
        seed: of the new grains' lattice jitter and radii.
        chimney: once the window travels, the grains within this many cone radii of the axis
            stay grains up to the free surface (:meth:`MovingWindowPenetration.
            _window_shape`); 0: the whole width becomes continuum behind the tip, under a
            ghost band.
    """

    depth: float = 0.08
    trigger: float = 18.0         # the scene's (benchmarks/results/moving_window.json compares 6-18)
    step: float = 6.0
    max_height: float | None = None
    settle_steps: int = 8000
    servo_cycles: int = 30
    servo_rate: float = 0.005
    settle_hold: float = 4.0
    relax_iterations: int = 200
    overlap_tolerance: float = 1e-3
    max_moves: int = 50
    seed: int = 7
    chimney: float = 2.5

    def __post_init__(self):
        if not (np.isfinite(self.settle_hold) and self.settle_hold >= 0):
            raise ValueError(f"settle_hold must be >= 0, got {self.settle_hold!r}")
        if not (np.isfinite(self.chimney) and self.chimney >= 0):
            raise ValueError(f"chimney must be >= 0 cone radii, got {self.chimney!r}")
        for name in ("depth", "trigger", "step", "overlap_tolerance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if self.max_height is not None and not (np.isfinite(self.max_height) and self.max_height > 0):
            raise ValueError(f"max_height must be None or > 0 m, got {self.max_height!r}")
        if not (np.isfinite(self.servo_rate) and 0 <= self.servo_rate < 0.5):
            raise ValueError(f"servo_rate must lie in [0, 0.5), got {self.servo_rate!r}")
        for name in ("settle_steps", "servo_cycles", "relax_iterations", "max_moves"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
