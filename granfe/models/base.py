"""The contract of a continuum model.

A model is one small unit: it declares its fields (names, value shapes, default degrees),
its material constants as ``fem.Constant`` (so load stepping never recompiles a form), the
virtual work of its internal forces and of its inertia, its stresses for output, its rigid
modes (the near-nullspace of an AMG preconditioner, and the modes a reaction moment is
measured against), whether its residual is linear in the fields, and the variables it keeps
at quadrature points between steps (none for an elastic model). The problem, the time
stepper, the solvers and the writer work over any model through this contract only.

Conventions for a model's UFL callables: ``w``, ``dw``, ``a`` are tuples with one UFL
expression per field, in the order of :meth:`ContinuumModel.fields`; ``state`` maps the
names of :meth:`ContinuumModel.state_variables` to the committed values (quadrature
functions), and is empty for a model without history.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

__all__ = ["Field", "ContinuumModel"]


@dataclass(frozen=True)
class Field:
    """One unknown field of a model.

    Attributes:
        name: e.g. ``"u"`` or ``"phi"``; boundary conditions and outputs use it.
        shape: value shape, ``()`` for a scalar field.
        components: names of its scalar components in storage order (``("u_x", "u_y")``);
            for a scalar field, other names of the field itself (``("phi_z",)``).
        degree: default Lagrange degree.
    """

    name: str
    shape: tuple[int, ...]
    components: tuple[str, ...] = ()
    degree: int = 1


class ContinuumModel:
    """Base class of continuum models; subclasses fill in the physics.

    A subclass sets :attr:`name` (its registry key), :attr:`linear` (residual affine in the
    fields for fixed state, so a time step may be solved with one factorisation) and
    :attr:`material_type`, and implements :meth:`fields`, :meth:`constant_values`,
    :meth:`internal_work`, :meth:`inertia_work`, :meth:`stresses` and :meth:`rigid_modes`;
    a history-dependent model also implements :meth:`state_variables` and
    :meth:`state_update`.
    """

    name: ClassVar[str] = ""
    linear: ClassVar[bool] = True
    material_type: ClassVar[type] = object
    #: PETSc options the model's residual needs (a problem's own options override them)
    solver_options: ClassVar[dict] = {}
    #: dolfinx JIT options for the model's forms and expressions (e.g. lower C optimisation
    #: for a very long kernel: gcc -O2 needs minutes on a dense finite-strain Hessian)
    jit_options: ClassVar[dict] = {}

    def __init__(self, material):
        if not isinstance(material, self.material_type):
            raise TypeError(f"the {self.name} model takes a {self.material_type.__name__}, "
                            f"got {type(material).__name__}")
        self.material = material
        self.constants = None
        self.gdim = None

    # ---- set-up ---------------------------------------------------------------------
    def bind(self, domain) -> None:
        """Create the constants on ``domain`` (called once by the problem)."""
        self.gdim = domain.geometry.dim
        if self.gdim not in self.dimensions():
            raise ValueError(f"the {self.name} model runs in {self.dimensions()} dimensions, "
                             f"the mesh has {self.gdim}")
        self.constants = self.make_constants(domain)

    def dimensions(self) -> tuple[int, ...]:
        return (2, 3)

    def fixed_fields(self) -> tuple:
        """Functions in the model's forms that a run sets between steps only rarely (e.g. a
        mask set once): a linear model's time step may then still be factorised once, the
        factors renewed when their values change (:class:`granfe.dynamics.GeneralizedAlpha`).
        None by default."""
        return ()

    def update(self, material) -> None:
        """Change the material in place (``fem.Constant`` values; no recompilation)."""
        if not isinstance(material, self.material_type):
            raise TypeError(f"expected a {self.material_type.__name__}, got {type(material).__name__}")
        self.material = material
        for name, value in self.constant_values(material).items():
            getattr(self.constants, name).value = value

    # ---- declarations ---------------------------------------------------------------
    def fields(self, gdim: int) -> tuple[Field, ...]:
        raise NotImplementedError

    def make_constants(self, domain):
        """The constants of :meth:`constant_values` as ``fem.Constant`` attributes of a
        namespace (a model may return its own typed container instead)."""
        from types import SimpleNamespace

        from dolfinx import default_scalar_type, fem

        return SimpleNamespace(**{k: fem.Constant(domain, default_scalar_type(v))
                                  for k, v in self.constant_values(self.material).items()})

    def constant_values(self, material) -> dict[str, float]:
        raise NotImplementedError

    def state_variables(self, gdim: int) -> dict[str, tuple[int, ...]]:
        """Quadrature-point variables kept between steps: name -> value shape."""
        return {}

    # ---- physics (UFL) --------------------------------------------------------------
    def internal_work(self, w: tuple, dw: tuple, state: dict):
        """Virtual work density of the internal forces for test functions ``dw``."""
        raise NotImplementedError

    def inertia_work(self, a: tuple, dw: tuple):
        """Virtual work density of the inertial forces for accelerations ``a``."""
        raise NotImplementedError

    def kinetic_energy(self, v: tuple):
        """Kinetic energy density for velocities ``v``."""
        raise NotImplementedError

    def stored_energy(self, w: tuple, state: dict):
        """Stored (elastic) energy density."""
        raise NotImplementedError

    def stresses(self, w: tuple, state: dict) -> dict:
        """Named stress measures (UFL) for output, e.g. ``{"sigma": ..., "couple_stress": ...}``."""
        raise NotImplementedError

    def state_update(self, w: tuple, state: dict) -> dict:
        """The trial state reached from the committed ``state`` by the fields ``w`` (UFL)."""
        return {}

    def rigid_modes(self, gdim: int) -> list[tuple[Callable | None, ...]]:
        """Rigid-body modes: per mode one interpolation callable ``x -> values`` per field
        (None for a zero field); the gdim translations first, then the rotations about the
        origin (:meth:`~granfe.problem.ContinuumProblem.reaction_moment` reads them so)."""
        raise NotImplementedError

    def plot_fields(self, w: tuple, state: dict) -> dict:
        """Named scalar fields for pictures; components and magnitudes by default."""
        out = {}
        for f, value in zip(self.fields(self.gdim), w, strict=True):
            if f.shape == ():
                out[f.name] = value
                continue
            import ufl

            out[f"{f.name}_magnitude"] = ufl.sqrt(ufl.inner(value, value))
            for i, c in enumerate(f.components):
                out[c] = value[i]
        return out
