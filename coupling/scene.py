"""Scenes: TOML files describing a coupled run, validated on load.

A scene is one table per concern (``[scene]``, ``[geometry]``, ``[particles]``,
``[window]``, ``[penetrator]``, ``[solver]``, ``[output]``), each a frozen dataclass of
typed defaults. Layering (pyro2 / FFCx style): dataclass defaults, then the TOML file,
then ``--set section.key=value`` overrides. An unknown section or key, a value of the wrong
type, or a value out of range raises :class:`SceneError` naming ``section.key``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from coupling.applications import APPLICATIONS, application

__all__ = ["SceneError", "Scene", "load_scene", "parse_overrides", "KINDS"]

KINDS = tuple(APPLICATIONS)


class SceneError(ValueError):
    """A scene file problem; the message names the key (``section.key``) and the rule."""


def _positive(section, name, value):
    if not (math.isfinite(value) and value > 0):
        raise SceneError(f"{section}.{name} must be > 0, got {value!r}")


def _in_range(key, value, lo, hi, text, upper_open=False):
    ok = math.isfinite(value) and lo <= value and (value < hi if upper_open else value <= hi)
    if not ok:
        raise SceneError(f"{key} must lie in {text}, got {value!r}")


@dataclass(frozen=True)
class SceneInfo:
    name: str = "scene"
    kind: str = "bonded_punch"
    dimension: int = 2

    def __post_init__(self):
        if not self.name or self.name in (".", "..") or any(c in self.name for c in "/\0"):
            raise SceneError(f"scene.name must be a plain name (it names the output directory), "
                             f"got {self.name!r}")
        if self.kind not in KINDS:
            raise SceneError(f"scene.kind must be one of {list(KINDS)}, got {self.kind!r}")
        allowed = APPLICATIONS[self.kind].dimensions
        if self.dimension not in allowed:
            raise SceneError(f"scene.dimension must be one of {list(allowed)} for kind {self.kind!r}, "
                             f"got {self.dimension!r}")


@dataclass(frozen=True)
class Geometry:
    """Block of grains and continuum [m]."""

    width: float = 0.4
    height: float = 0.2
    element_size: float = 0.01
    degree_u: int = 2
    degree_phi: int = 2

    def __post_init__(self):
        for n in ("width", "height", "element_size"):
            _positive("geometry", n, getattr(self, n))
        if self.element_size > min(self.width, self.height) / 2:
            raise SceneError(f"geometry.element_size = {self.element_size} is larger than half the "
                             f"block ({min(self.width, self.height) / 2})")
        for n in ("degree_u", "degree_phi"):
            if getattr(self, n) not in (1, 2):
                raise SceneError(f"geometry.{n} must be 1 or 2, got {getattr(self, n)!r}")


@dataclass(frozen=True)
class Particles:
    """Bonded hexagonal packing: radius [m], bond stiffnesses [N/m], k_r = kr_factor k_t d^2."""

    radius: float = 0.002
    kn: float = 1.0e8
    kt: float = 3.0e7
    kr_factor: float = 0.1

    def __post_init__(self):
        for n in ("radius", "kn"):
            _positive("particles", n, getattr(self, n))
        for n in ("kt", "kr_factor"):
            if not (math.isfinite(getattr(self, n)) and getattr(self, n) >= 0):
                raise SceneError(f"particles.{n} must be >= 0, got {getattr(self, n)!r}")
        if self.kt >= self.kn:
            raise SceneError(f"particles.kt = {self.kt} must be below particles.kn = {self.kn} "
                             "(the lattice's lambda = sqrt(3)/4 (kn - kt) must stay positive)")


@dataclass(frozen=True)
class Window:
    """DE window around the penetrator [m]; ghost band in grain diameters, overlap in elements."""

    half_width: float = 0.06
    depth: float = 0.06
    ghost_width: float = 2.5
    handshake: float = 1.0

    def __post_init__(self):
        for n in ("half_width", "depth", "ghost_width", "handshake"):
            _positive("window", n, getattr(self, n))
        if self.ghost_width < 1.0:
            raise SceneError(f"window.ghost_width = {self.ghost_width} grain diameters is too thin: "
                             "a free grain's bonded neighbours must all be simulated (>= 1)")


@dataclass(frozen=True)
class Penetrator:
    """Rough flat punch pushed into the top surface: width [m], final settlement [m], steps."""

    shape: str = "flat_punch"
    width: float = 0.04
    settlement: float = 1.0e-4
    steps: int = 5

    def __post_init__(self):
        if self.shape != "flat_punch":
            raise SceneError(f"penetrator.shape must be 'flat_punch' for a bonded scene, got {self.shape!r}")
        _positive("penetrator", "width", self.width)
        _positive("penetrator", "settlement", self.settlement)
        if not (isinstance(self.steps, int) and self.steps >= 1):
            raise SceneError(f"penetrator.steps must be an integer >= 1, got {self.steps!r}")


@dataclass(frozen=True)
class Solver:
    tol: float = 1e-8
    max_iterations: int = 300
    cutbacks: int = 3

    def __post_init__(self):
        if not 0 < self.tol < 1:
            raise SceneError(f"solver.tol must lie in (0, 1), got {self.tol!r}")
        if self.max_iterations < 1:
            raise SceneError(f"solver.max_iterations must be >= 1, got {self.max_iterations!r}")
        if self.cutbacks < 0:
            raise SceneError(f"solver.cutbacks must be >= 0, got {self.cutbacks!r}")


@dataclass(frozen=True)
class Output:
    every: int = 1
    fields: bool = True
    particles: bool = True
    png: bool = True

    def __post_init__(self):
        if self.every < 1:
            raise SceneError(f"output.every must be >= 1, got {self.every!r}")


class _Tables:
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_toml(self) -> str:
        lines = []
        for section, values in self.to_dict().items():
            lines.append(f"[{section}]")
            for k, v in values.items():
                lines.append(f"{k} = {_toml_value(v)}")
            lines.append("")
        return "\n".join(lines)


@dataclass(frozen=True)
class Scene(_Tables):
    """A ``bonded_punch`` scene: a rough punch into bonded grains (quasi-static)."""

    scene: SceneInfo = field(default_factory=SceneInfo)
    geometry: Geometry = field(default_factory=Geometry)
    particles: Particles = field(default_factory=Particles)
    window: Window = field(default_factory=Window)
    penetrator: Penetrator = field(default_factory=Penetrator)
    solver: Solver = field(default_factory=Solver)
    output: Output = field(default_factory=Output)

    def __post_init__(self):
        g, w, p = self.geometry, self.window, self.penetrator
        if w.half_width >= g.width / 2 or w.depth >= g.height:
            raise SceneError(
                f"window (half_width {w.half_width}, depth {w.depth}) is not covered by the "
                f"continuum block (width {g.width}, height {g.height}): the mesh must cover the "
                "DE window and its ghost band")
        if p.width / 2 >= w.half_width:
            raise SceneError(f"penetrator.width = {p.width} does not fit inside the window "
                             f"(half_width {w.half_width})")
        if 2 * self.particles.radius > g.element_size:
            raise SceneError(f"particles.radius = {self.particles.radius}: grains larger than "
                             f"geometry.element_size = {g.element_size} leave FE nodes of the "
                             "overlap without grains (the L2 projection needs several per element)")



# ---- penetration scenes ----------------------------------------------------------------------
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
    """The DE window follows the penetrator (:mod:`coupling.moving_window`, seed 000 Fig. 3):
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
        """The :class:`coupling.moving_window.MovingWindowParameters` of this scene, or None
        when the window does not follow the penetrator."""
        from coupling.moving_window import MovingWindowParameters, refined_depth

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
        """The :class:`coupling.penetration.PenetrationParameters` of this scene."""
        from coupling.penetration import PenetrationParameters

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


def _named(message: str, keys: dict) -> str:
    """``message`` with its leading parameter name replaced by the scene's section.key."""
    for name, key in sorted(keys.items(), key=lambda kv: -len(kv[0])):
        if message.startswith(name):
            return key + message[len(name):]
    return message


def _toml_value(v):
    """``v`` as a TOML value that :mod:`tomllib` reads back equal."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
    return repr(v)


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}


def _toml_string(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _coerce(section: str, key: str, value, expected_type):
    if expected_type is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected_type is bool and not isinstance(value, bool):
        raise SceneError(f"{section}.{key} must be true or false, got {value!r}")
    if expected_type is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise SceneError(f"{section}.{key} must be an integer, got {value!r}")
    if not isinstance(value, expected_type):
        raise SceneError(f"{section}.{key} must be a {expected_type.__name__}, got {value!r}")
    return value


def _build(data: dict):
    info = data.get("scene")
    kind = info.get("kind", "bonded_punch") if isinstance(info, dict) else "bonded_punch"
    try:
        app = application(kind)
    except ValueError as err:
        raise SceneError(str(err)) from None
    schema = app.load("scene")
    _SECTIONS = {f.name: type(f.default_factory()) for f in fields(schema)}
    sections = {}
    for name, values in data.items():
        if name not in _SECTIONS:
            raise SceneError(f"unknown section [{name}]; known sections: {sorted(_SECTIONS)}")
        if not isinstance(values, dict):
            raise SceneError(f"[{name}] must be a table")
        cls = _SECTIONS[name]
        types = {f.name: eval(f.type, {}, {}) if isinstance(f.type, str) else f.type  # noqa: S307
                 for f in fields(cls)}
        for key in values:
            if key not in types:
                raise SceneError(f"unknown key {name}.{key}; known keys of [{name}]: {sorted(types)}")
        kwargs = {k: _coerce(name, k, v, types[k]) for k, v in values.items()}
        if name == "scene":
            kwargs.setdefault("name", app.default_name)
        sections[name] = cls(**kwargs)
    return schema(**sections)


def parse_overrides(items: list[str]) -> dict:
    """``["window.half_width=0.08", ...]`` -> nested dict (values parsed as TOML)."""
    out: dict = {}
    for item in items or []:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise SceneError(f"--set expects section.key=value, got {item!r}")
        path, value = item.split("=", 1)
        section, key = path.strip().split(".", 1)
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            parsed = value.strip()  # bare strings
        out.setdefault(section, {})[key] = parsed
    return out


def load_scene(path: str | Path | None = None, overrides: dict | None = None):
    """Scene from a TOML file (or defaults) with overrides; raises :class:`SceneError`."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.exists():
            raise SceneError(f"scene file {path} does not exist")
        if path.is_dir():
            raise SceneError(f"{path} is a directory, not a scene file (to continue a run in it: "
                             f"granfe restart {path})")
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as err:
            raise SceneError(f"{path} is not valid TOML: {err}") from None
        except UnicodeDecodeError:
            raise SceneError(f"{path} is not a text (UTF-8 TOML) scene file") from None
        except OSError as err:
            raise SceneError(f"cannot read {path}: {err.strerror or err}") from None
    for section, values in (overrides or {}).items():
        data.setdefault(section, {}).update(values)
    return _build(data)
