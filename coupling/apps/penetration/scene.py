"""The tables of a ``penetration`` scene: a cone or pile pushed into frictional grains."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from coupling.scene import SceneError, SceneInfo, _in_range, _named, _positive, _Tables

__all__ = ["PenetrationScene"]


@dataclass(frozen=True)
class Chamber:
    """Continuum chamber [m] (width: the diameter of the 3D cylinder) and its element sizes
    (fine at the window, coarse far)."""

    width: float = 0.3
    depth: float = 0.2
    element_size_window: float = 0.008
    element_size_far: float = 0.04

    def __post_init__(self):
        for n in ("width", "depth", "element_size_window", "element_size_far"):
            _positive("chamber", n, getattr(self, n))
        if self.element_size_window > self.element_size_far:
            raise SceneError(f"chamber.element_size_window = {self.element_size_window} is coarser "
                             f"than chamber.element_size_far = {self.element_size_far}: the mesh "
                             "is refined toward the window, not away from it")
        if self.element_size_far > min(self.width, self.depth):
            raise SceneError(f"chamber.element_size_far = {self.element_size_far} is larger than "
                             f"the chamber (width {self.width}, depth {self.depth})")


@dataclass(frozen=True)
class Grains:
    """Grains: radius [m] (reduced by up to ``jitter``), Coulomb friction, restitution;
    settled for ``settle_time`` [s] under gravity. 2D disks: linear contacts kn [N/m per m],
    kt/kn. 3D spheres: Hertz-Mindlin with Young's modulus ``youngs_modulus`` [Pa] and nu."""

    radius: float = 1.5e-3
    jitter: float = 0.1
    kn: float = 2.0e5
    kt_over_kn: float = 0.5
    nu: float = 0.25
    density: float = 2650.0
    friction: float = 0.5
    restitution: float = 0.5
    settle_time: float = 0.3
    gravity: float = 9.81
    seed: int = 1
    youngs_modulus: float = 2.9e7

    def __post_init__(self):
        for n in ("radius", "kn", "density", "settle_time", "youngs_modulus"):
            _positive("grains", n, getattr(self, n))
        _in_range("grains.friction", self.friction, 0.0, math.inf, "[0, inf)")
        _in_range("grains.kt_over_kn", self.kt_over_kn, 0.0, math.inf, "[0, inf)")
        _in_range("grains.jitter", self.jitter, 0.0, 0.5, "[0, 0.5)", upper_open=True)
        if not (0.0 < self.restitution <= 1.0):
            raise SceneError(f"grains.restitution must lie in (0, 1], got {self.restitution!r}")
        if not (-1.0 < self.nu < 0.5):
            raise SceneError(f"grains.nu must lie in (-1, 0.5), got {self.nu!r}")
        if not math.isfinite(self.gravity):
            raise SceneError(f"grains.gravity must be finite, got {self.gravity!r}")
        if self.seed < 0:
            raise SceneError(f"grains.seed must be an integer >= 0, got {self.seed!r}")


@dataclass(frozen=True)
class PenetrationWindow:
    half_width: float = 0.04
    depth: float = 0.08
    ghost_width: float = 2.5
    handshake: float = 2.0

    def __post_init__(self):
        for n in ("half_width", "depth", "ghost_width", "handshake"):
            _positive("window", n, getattr(self, n))
        if self.ghost_width < 1.0:
            raise SceneError(f"window.ghost_width = {self.ghost_width} grain diameters is too "
                             "thin: the ghost band holds the window's grains (>= 1 diameter)")


@dataclass(frozen=True)
class Cone:
    """Penetrator: ``cone`` (60 degree apex by default; the 2D section in 2D) or ``pile``
    (flat end, 3D): radius [m], apex angle [deg], velocity [m/s], depth [m]."""

    shape: str = "cone"
    radius: float = 0.01
    apex_deg: float = 60.0
    velocity: float = 0.2
    depth: float = 0.04

    def __post_init__(self):
        if self.shape not in ("cone", "pile"):
            raise SceneError(f"penetrator.shape must be 'cone' or 'pile' for a penetration scene, "
                             f"got {self.shape!r}")
        for n in ("radius", "velocity", "depth"):
            _positive("penetrator", n, getattr(self, n))
        if not (10.0 <= self.apex_deg <= 180.0):
            raise SceneError(f"penetrator.apex_deg must lie in [10, 180] degrees, "
                             f"got {self.apex_deg!r}")


@dataclass(frozen=True)
class Exchange:
    """DE sub-steps per FE step and the relaxation of the prescribed FE values."""

    substeps: int = 50
    relaxation: float = 0.3

    def __post_init__(self):
        if self.substeps < 1:
            raise SceneError(f"coupling.substeps must be >= 1, got {self.substeps!r}")
        if not 0 < self.relaxation <= 1:
            raise SceneError(f"coupling.relaxation must lie in (0, 1], got {self.relaxation!r}")


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
    trigger: float = 18.0
    step: float = 6.0
    max_height: float = 0.0
    chimney: float = 2.5
    settle_steps: int = 8000
    servo_rate: float = 0.005


# MovingWindowParameters field -> section.key of the scene
_FOLLOW_KEYS = {"depth": "penetrator.depth", "trigger": "follow.trigger", "step": "follow.step",
                "max_height": "follow.max_height", "chimney": "follow.chimney",
                "settle_steps": "follow.settle_steps", "servo_rate": "follow.servo_rate"}

# PenetrationParameters field -> section.key of the scene
_PENETRATION_KEYS = {
    "chamber_width": "chamber.width", "chamber_depth": "chamber.depth",
    "element_size_window": "chamber.element_size_window",
    "element_size_far": "chamber.element_size_far",
    "window_half_width": "window.half_width", "window_depth": "window.depth",
    "ghost_width": "window.ghost_width", "handshake": "window.handshake",
    "radius": "grains.radius", "jitter": "grains.jitter", "kn": "grains.kn",
    "kt_over_kn": "grains.kt_over_kn", "nu": "grains.nu", "density": "grains.density",
    "friction": "grains.friction", "restitution": "grains.restitution",
    "settle_time": "grains.settle_time", "gravity": "grains.gravity", "seed": "grains.seed",
    "cone_radius": "penetrator.radius", "apex_deg": "penetrator.apex_deg",
    "velocity": "penetrator.velocity", "depth": "penetrator.depth",
    "substeps": "coupling.substeps", "relaxation": "coupling.relaxation",
    "dim": "scene.dimension", "shape": "penetrator.shape", "youngs_modulus": "grains.youngs_modulus",
}


@dataclass(frozen=True)
class PenetrationScene(_Tables):
    """A ``penetration`` scene: a cone or pile pushed into frictional grains coupled to the
    continuum, 2D or 3D (``scene.dimension``)."""

    scene: SceneInfo = field(default_factory=lambda: SceneInfo(name="cpt_2d", kind="penetration"))
    chamber: Chamber = field(default_factory=Chamber)
    grains: Grains = field(default_factory=Grains)
    window: PenetrationWindow = field(default_factory=PenetrationWindow)
    penetrator: Cone = field(default_factory=Cone)
    coupling: Exchange = field(default_factory=Exchange)
    output: PenetrationOutput = field(default_factory=PenetrationOutput)
    follow: Follow = field(default_factory=Follow)

    def __post_init__(self):
        self.parameters()  # validate the combination, naming the scene key
        self._check_sizes()
        if self.follow.enabled:
            self.moving_parameters()
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

    def moving_parameters(self):
        """The :class:`coupling.apps.penetration.moving_window.MovingWindowParameters` of this scene, or None
        when the window does not follow the penetrator."""
        from coupling.apps.penetration.moving_window import MovingWindowParameters, refined_depth

        f = self.follow
        if not f.enabled:
            return None
        try:
            mv = MovingWindowParameters(
                depth=self.penetrator.depth, trigger=f.trigger, step=f.step,
                max_height=f.max_height if f.max_height > 0 else None, chimney=f.chimney,
                settle_steps=f.settle_steps, servo_rate=f.servo_rate)
        except ValueError as err:
            raise SceneError(_named(str(err), _FOLLOW_KEYS)) from None
        try:
            refined_depth(self.parameters(), mv)
        except ValueError as err:
            raise SceneError(_named(str(err), {"chamber_depth": "chamber.depth"})) from None
        return mv

    def parameters(self):
        """The :class:`coupling.apps.penetration.coupled.PenetrationParameters` of this scene."""
        from coupling.apps.penetration.coupled import PenetrationParameters

        c, g, w, p, x = self.chamber, self.grains, self.window, self.penetrator, self.coupling
        values = dict(
            chamber_width=c.width, chamber_depth=c.depth, element_size_window=c.element_size_window,
            element_size_far=c.element_size_far, window_half_width=w.half_width,
            window_depth=w.depth, ghost_width=w.ghost_width, handshake=w.handshake,
            radius=g.radius, jitter=g.jitter, kn=g.kn, kt_over_kn=g.kt_over_kn, nu=g.nu,
            density=g.density, friction=g.friction, restitution=g.restitution,
            settle_time=g.settle_time, gravity=g.gravity, seed=g.seed, cone_radius=p.radius,
            apex_deg=p.apex_deg, velocity=p.velocity, depth=p.depth, substeps=x.substeps,
            relaxation=x.relaxation, dim=self.scene.dimension, shape=p.shape,
            youngs_modulus=g.youngs_modulus)
        if self.follow.enabled:
            # the initial window holds half its depth of the push (the window then follows)
            values["depth"] = min(p.depth, max(0.5 * (w.depth - 2 * p.radius), 1e-3 * w.depth))
        try:
            return PenetrationParameters(**values)
        except ValueError as err:
            raise SceneError(_named(str(err), _PENETRATION_KEYS)) from None
