"""The micropolar UFL algebra, kept under its old name: it lives in
:mod:`granfe.models.micropolar` with the model it belongs to."""

from granfe.models.micropolar import (
                                      MaterialConstants,
                                      curvature,
                                      inertia_work,
                                      internal_work,
                                      kinetic_energy_density,
                                      strain,
                                      strain_energy_density,
                                      stresses,
                                      zero_vector,
)

__all__ = ["MaterialConstants", "strain", "curvature", "strain_energy_density", "stresses",
           "internal_work", "inertia_work", "kinetic_energy_density", "zero_vector"]
