"""The tables of a ``bonded_punch`` scene: a rough punch into bonded grains."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from coupling.scene import SceneError, SceneInfo, _positive, _Tables

__all__ = ["Scene"]


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
