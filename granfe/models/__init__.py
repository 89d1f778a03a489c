"""Continuum models, one file each, found by name in :data:`MODELS`.

Adding a model: one file in this package with a :class:`~granfe.models.base.ContinuumModel`
subclass (and its material dataclass), plus one row in :data:`MODELS`.
"""

from granfe.models.base import ContinuumModel, Field
from granfe.models.drucker_prager import MicropolarDruckerPrager
from granfe.models.micromorphic import Micromorphic
from granfe.models.micromorphic_drucker_prager import MicromorphicDruckerPrager
from granfe.models.micromorphic_finite import MicromorphicFiniteStrain
from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
from granfe.models.micromorphic_iterative import MicromorphicDruckerPragerIterative
from granfe.models.micropolar import Micropolar
from granfe.models.poroelastic import MicropolarPoroelastic, Poroelastic
from granfe.models.quadrature_stress import QuadratureStress
from granfe.models.strain_memory import StrainMemory

__all__ = ["ContinuumModel", "Field", "MODELS", "model_class", "Micromorphic", "MicromorphicDruckerPrager",
           "MicromorphicDruckerPragerIterative", "MicromorphicFiniteDruckerPrager", "MicromorphicFiniteStrain",
           "Micropolar", "MicropolarDruckerPrager", "MicropolarPoroelastic", "Poroelastic", "QuadratureStress",
           "StrainMemory"]

MODELS: dict[str, type[ContinuumModel]] = {
    Micropolar.name: Micropolar,
    StrainMemory.name: StrainMemory,
    MicropolarDruckerPrager.name: MicropolarDruckerPrager,
    Micromorphic.name: Micromorphic,
    MicromorphicFiniteStrain.name: MicromorphicFiniteStrain,
    MicromorphicDruckerPrager.name: MicromorphicDruckerPrager,
    MicromorphicDruckerPragerIterative.name: MicromorphicDruckerPragerIterative,
    MicromorphicFiniteDruckerPrager.name: MicromorphicFiniteDruckerPrager,
    Poroelastic.name: Poroelastic,
    MicropolarPoroelastic.name: MicropolarPoroelastic,
    QuadratureStress.name: QuadratureStress,
}


def model_class(name: str) -> type[ContinuumModel]:
    """The model registered under ``name``."""
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"unknown continuum model {name!r}; known: {sorted(MODELS)}") from None
