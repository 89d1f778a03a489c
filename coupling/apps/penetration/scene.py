"""The tables of a ``penetration`` scene: a cone or pile pushed into frictional grains.

Every key that sets a run parameter is a :func:`~coupling.scene.parameter` of
:class:`~coupling.apps.penetration.parameters.PenetrationParameters` or
:class:`~coupling.apps.penetration.parameters.MovingWindowParameters`: defaults, ranges and
messages are stated there once; the tables only say where each key lives.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from coupling.apps.penetration.fluid import BIOT_3D
from coupling.apps.penetration.fluid import FluidParameters as F
from coupling.apps.penetration.parameters import MovingWindowParameters as M
from coupling.apps.penetration.parameters import PenetrationParameters as P
from coupling.scene import SceneError, SceneInfo, _named, _Tables, parameter, parameter_keys, parameter_values

__all__ = ["PenetrationScene"]


@dataclass(frozen=True)
class Chamber:
    """Continuum chamber [m] (width: the diameter of the 3D cylinder) and its element sizes
    (fine at the window, coarse far). 2D calibration-chamber loading
    (:mod:`coupling.apps.penetration.chamber`): ``vertical_stress`` [Pa] on the top grains
    (0: a free surface), consolidated to an unbalanced-force ratio ``consolidation_tol``;
    ``lateral`` = "rigid" (BC3, zero lateral strain) or "stress" (BC1, constant lateral
    stress)."""

    width: float = parameter(P, "chamber_width")
    depth: float = parameter(P, "chamber_depth")
    element_size_window: float = parameter(P, "element_size_window")
    element_size_far: float = parameter(P, "element_size_far")
    vertical_stress: float = parameter(P, "vertical_stress")
    lateral: str = parameter(P, "lateral")
    consolidation_tol: float = parameter(P, "consolidation_tol")
    consolidation_max_steps: int = parameter(P, "consolidation_max_steps")


@dataclass(frozen=True)
class Grains:
    """Grains: radius [m] (reduced by up to ``jitter``), Coulomb friction, restitution;
    settled for ``settle_time`` [s] under gravity. 2D disks: linear contacts kn [N/m per m],
    kt/kn. 3D spheres: Hertz-Mindlin with Young's modulus ``youngs_modulus`` [Pa] and nu."""

    radius: float = parameter(P, "radius")
    jitter: float = parameter(P, "jitter")
    kn: float = parameter(P, "kn")
    kt_over_kn: float = parameter(P, "kt_over_kn")
    nu: float = parameter(P, "nu")
    density: float = parameter(P, "density")
    friction: float = parameter(P, "friction")
    restitution: float = parameter(P, "restitution")
    settle_time: float = parameter(P, "settle_time")
    gravity: float = parameter(P, "gravity")
    seed: int = parameter(P, "seed")
    youngs_modulus: float = parameter(P, "youngs_modulus")


@dataclass(frozen=True)
class PenetrationWindow:
    """DE window [m] about the axis; ghost band in grain diameters, overlap in elements."""

    half_width: float = parameter(P, "window_half_width")
    depth: float = parameter(P, "window_depth")
    ghost_width: float = parameter(P, "ghost_width")
    handshake: float = parameter(P, "handshake")


@dataclass(frozen=True)
class Cone:
    """Penetrator: ``cone`` (60 degree apex by default; the 2D section in 2D) or ``pile``
    (flat end, 3D): radius [m], apex angle [deg], velocity [m/s], depth [m]."""

    shape: str = parameter(P, "shape")
    radius: float = parameter(P, "cone_radius")
    apex_deg: float = parameter(P, "apex_deg")
    velocity: float = parameter(P, "velocity")
    depth: float = parameter(P, "depth")


@dataclass(frozen=True)
class ContinuumModel:
    """The continuum's model: ``micropolar`` (elastic, constants from the settled grains) or
    ``micropolar_drucker_prager`` (those constants and a Drucker-Prager cone matched to
    Mohr-Coulomb in plane strain: friction and dilatancy [deg], cohesion [Pa]; 2D chambers
    under a vertical stress). ``constants`` (2D): ``lattice`` (the bonded hexagonal lattice
    scaled by the window's coordination) or ``calibrated`` (element tests on a periodic cell
    of the grains at the window's mean stress, :mod:`coupling.calibration`; its peak friction
    and dilatancy angles then replace ``friction_deg`` and ``dilatancy_deg``); 3D: ``lattice``
    (the affine estimate of the settled contacts), ``calibrated``, ``window`` (that estimate
    scaled to the window's constrained modulus, probed in situ) or ``window_isotropic`` (lam
    and the shear modulus both from that probe: its lateral stress too). ``hardening``
    [Pa]: the cone's cohesion grows by it per unit equivalent plastic strain (perfect
    plasticity lets a displacement-driven window drift with its grains). ``integrator``:
    ``implicit`` (generalized-alpha) or ``explicit`` (central differences on a lumped mass,
    substepped below the measured stability limit: no solve, which makes a plastic far field
    cheap, `granfe.explicit`); ``damping`` [1/s]: the explicit continuum's mass-proportional
    damping (its fundamental mode's damping ratio is damping / (2 omega)). ``micromorphic``:
    u and the micro-deformation phi = chi - I,
    the elastic constants above with ``micro_stiffness`` = b / G, the stiffness of the
    symmetric relative deformation sym(grad u - phi) over the classical shear modulus (its
    limit b -> inf is the micropolar solid); phi at the window's nodes fitted to the grains'
    displacements, the ghosts' rotation skew(phi)'s axial vector (`coupling.micro_kinematics`).
    ``micromorphic_drucker_prager``: that solid with the Drucker-Prager cone above
    (``friction_deg``, ``dilatancy_deg``, ``cohesion``, ``hardening``; compression meridian)
    on its macro stress, the levels returned together at the points (its moduli couple
    them); 3D free surface only (``chamber.vertical_stress = 0``: the continuum's geostatic
    solve gives the total stress the cone needs)."""

    model: str = parameter(P, "continuum")
    constants: str = parameter(P, "continuum_constants")
    friction_deg: float = parameter(P, "continuum_friction_deg")
    dilatancy_deg: float = parameter(P, "continuum_dilatancy_deg")
    cohesion: float = parameter(P, "continuum_cohesion")
    hardening: float = parameter(P, "continuum_hardening")
    integrator: str = parameter(P, "continuum_integrator")
    damping: float = parameter(P, "continuum_damping")
    micro_stiffness: float = parameter(P, "continuum_micro_stiffness")


@dataclass(frozen=True)
class Exchange:
    """DE sub-steps per FE step; the exchange (``interface``): ``loose``, one pass per FE step
    with the prescribed FE values relaxed by ``relaxation``, ``iqn-ils``, iterated within
    the FE step to ``interface_tol`` (interface quasi-Newton; ``relaxation`` is its first
    step), or ``forces``, one pass per FE step with the ghosts' reactions as the continuum's
    loads (relaxed by ``relaxation``) and nothing of it prescribed (`coupling.reactions`).
    ``dt_factor``: the DEM step over the law's default (0.05 of the critical step of
    the linear law, 0.2 Rayleigh for Hertz-Mindlin; up to 20 / 5). ``distribute_grains``
    (3D chambers): on more than one rank the push's grains are split over the ranks by space
    (`dem.DistributedSimulation`), not run whole on every rank."""

    substeps: int = parameter(P, "substeps")
    dt_factor: float = parameter(P, "dt_factor")
    relaxation: float = parameter(P, "relaxation")
    interface: str = parameter(P, "interface")
    interface_tol: float = parameter(P, "interface_tol")
    interface_max_iterations: int = parameter(P, "interface_max_iterations")
    distribute_grains: bool = parameter(P, "distribute_grains")


@dataclass(frozen=True)
class PenetrationOutput:
    """Frames of grains and continuum; a checkpoint every ``checkpoint_every`` FE steps
    (0: none; ``granfe restart`` continues from the last one)."""

    frames: int = 5
    fields: bool = True
    particles: bool = True
    png: bool = True
    checkpoint_every: int = 20

    def __post_init__(self):
        if self.frames < 1:
            raise SceneError(f"output.frames must be >= 1, got {self.frames!r}")
        if self.checkpoint_every < 0:
            raise SceneError(f"output.checkpoint_every must be >= 0, got {self.checkpoint_every!r}")


@dataclass(frozen=True)
class Follow:
    """The DE window follows the penetrator (:mod:`coupling.apps.penetration.moving_window`, seed 000 Fig. 3):
    off unless ``enabled``; then ``penetrator.depth`` is the whole push, which the initial
    window need not hold. ``trigger`` and ``step`` in grain diameters, ``max_height`` [m]
    (0: the window only grows), ``chimney`` in penetrator radii (0: none)."""

    enabled: bool = False
    trigger: float = parameter(M, "trigger")
    step: float = parameter(M, "step")
    max_height: float = parameter(M, "max_height", default=0.0)   # None has no TOML spelling
    chimney: float = parameter(M, "chimney")
    settle_steps: int = parameter(M, "settle_steps")
    servo_rate: float = parameter(M, "servo_rate")


@dataclass(frozen=True)
class Fluid:
    """A Darcy pore fluid through the window's grains and the chamber (:mod:`coupling.apps.
    penetration.saturated`; 2D and 3D, loose exchange, checkpoints with the fluid's state): off unless ``enabled``.
    ``permeability`` [m^2] (constant), ``viscosity`` [Pa s], ``compressibility`` [1/Pa],
    ``density`` [kg/m^3], ``saturation_time`` [s] the window takes its buoyancy before the
    push, ``every``: DEM steps per fluid step (dividing ``coupling.substeps``),
    ``continuum``: ``"biot"`` (the continuum in total stress, pushed by the pore pressure) or
    ``"drained"`` (the dry continuum), ``response_every``: DEM steps per application of the
    interval's forces (dividing ``every``; their impulse once per block)."""

    enabled: bool = False
    permeability: float = parameter(F, "permeability")
    viscosity: float = parameter(F, "viscosity")
    compressibility: float = parameter(F, "compressibility")
    density: float = parameter(F, "density")
    saturation_time: float = parameter(F, "saturation_time")
    every: int = parameter(F, "every")
    continuum: str = parameter(F, "continuum")
    response_every: int = parameter(F, "response_every")


@dataclass(frozen=True)
class PenetrationScene(_Tables):
    """A ``penetration`` scene: a cone or pile pushed into frictional grains coupled to the
    continuum, 2D or 3D (``scene.dimension``)."""

    scene: SceneInfo = field(default_factory=lambda: SceneInfo(name="cpt_2d", kind="penetration"))
    chamber: Chamber = field(default_factory=Chamber)
    grains: Grains = field(default_factory=Grains)
    window: PenetrationWindow = field(default_factory=PenetrationWindow)
    penetrator: Cone = field(default_factory=Cone)
    continuum: ContinuumModel = field(default_factory=ContinuumModel)
    coupling: Exchange = field(default_factory=Exchange)
    output: PenetrationOutput = field(default_factory=PenetrationOutput)
    follow: Follow = field(default_factory=Follow)
    fluid: Fluid = field(default_factory=Fluid)

    def __post_init__(self):
        self.parameters()  # validate the combination, naming the scene key
        self._check_sizes()
        self.fluid_parameters()
        if self.follow.enabled:
            self.moving_parameters()
            if self.continuum.model.startswith("micromorphic"):
                raise SceneError(f"continuum.model = {self.continuum.model!r} needs follow.enabled = "
                                 "false: the window that follows the penetrator prescribes no "
                                 "micro-deformation yet")
            if self.coupling.interface != "loose":
                raise SceneError(f"coupling.interface = {self.coupling.interface!r}: a window that "
                                 "follows the penetrator exchanges loosely so far (coupling.interface "
                                 "= 'loose' when follow.enabled = true)")
            if self.output.checkpoint_every:
                raise SceneError("output.checkpoint_every must be 0 when follow.enabled = true: a "
                                 "window that follows the penetrator writes no checkpoints yet")

    def _check_sizes(self):
        """The window against the chamber and its elements, grains against the elements."""
        c, g, w = self.chamber, self.grains, self.window
        d = 2 * g.radius
        bottom = w.depth + w.ghost_width * d + c.element_size_window
        if bottom >= c.depth:
            raise SceneError(f"window.depth = {w.depth} m (with its ghost band and an element "
                             f"below: {bottom:.4g} m) does not fit in chamber.depth = {c.depth} m")
        if c.element_size_window > 0.5 * min(w.half_width, w.depth):
            raise SceneError(f"chamber.element_size_window = {c.element_size_window} m is larger "
                             f"than half the window (window.half_width = {w.half_width}, "
                             f"window.depth = {w.depth}): no FE node of the window would be "
                             "prescribed by grains")
        if d > c.element_size_window:
            raise SceneError(f"grains.radius = {g.radius}: grains larger than "
                             f"chamber.element_size_window = {c.element_size_window} leave the "
                             "window's FE nodes without grains (the projection needs several "
                             "per element)")

    def fluid_parameters(self) -> F | None:
        """The :class:`~coupling.apps.penetration.fluid.FluidParameters` of this scene, or
        None when it is dry (no ``[fluid]``, or ``enabled = false``)."""
        if not self.fluid.enabled:
            return None
        try:
            fluid = F(**parameter_values(self, F))
        except ValueError as err:
            raise SceneError(_named(str(err), parameter_keys(self, F))) from None
        needs = {"coupling.interface = 'loose'": self.coupling.interface == "loose",
                 "follow.enabled = false": not self.follow.enabled}
        for need, ok in needs.items():
            if not ok:
                raise SceneError(f"fluid.enabled = true needs {need} (a saturated penetration "
                                 "exchanges loosely and keeps its window so far)")
        if self.coupling.substeps % fluid.every:
            raise SceneError(f"fluid.every = {fluid.every} DEM steps must divide coupling.substeps "
                             f"= {self.coupling.substeps}")
        prm = self.parameters()
        if fluid.continuum == "biot" and prm.dim != 2:
            raise SceneError(BIOT_3D)
        if fluid.continuum == "biot" and (prm.continuum_integrator != "implicit" or prm.continuum != "micropolar"):
            raise SceneError(f"fluid.continuum = 'biot' takes the implicit micropolar continuum so far "
                             f"(continuum.integrator = {prm.continuum_integrator!r}, continuum.model = "
                             f"{prm.continuum!r}); or fluid.continuum = 'drained'")
        return fluid

    def moving_parameters(self) -> M | None:
        """The :class:`~coupling.apps.penetration.parameters.MovingWindowParameters` of this
        scene, or None when the window does not follow the penetrator."""
        from coupling.apps.penetration.moving_window import refined_depth

        if not self.follow.enabled:
            return None
        values = parameter_values(self, M)
        values["depth"] = self.penetrator.depth          # the whole push
        values["max_height"] = values["max_height"] or None
        try:
            mv = M(**values)
        except ValueError as err:
            raise SceneError(_named(str(err), parameter_keys(self, M))) from None
        try:
            refined_depth(self.parameters(), mv)
        except ValueError as err:
            raise SceneError(_named(str(err), parameter_keys(self, P))) from None
        return mv

    def parameters(self) -> P:
        """The :class:`~coupling.apps.penetration.parameters.PenetrationParameters` of this scene."""
        values = parameter_values(self, P) | {"dim": self.scene.dimension}
        if self.follow.enabled:
            # the initial window holds half its depth of the push (the window then follows)
            w, p = self.window, self.penetrator
            values["depth"] = min(p.depth, max(0.5 * (w.depth - 2 * p.radius), 1e-3 * w.depth))
        try:
            return P(**values)
        except ValueError as err:
            keys = parameter_keys(self, P) | {"dim": "scene.dimension"}
            raise SceneError(_named(str(err), keys)) from None
