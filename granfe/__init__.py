"""granfe: the micropolar / micromorphic continuum (DOLFINx). Knows nothing of particles."""

from granfe.materials import MicropolarMaterial, lame_from_engineering

__all__ = ["MicropolarMaterial", "lame_from_engineering"]
