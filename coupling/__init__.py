"""coupling: bridging-scale DE x FE coupling, the one room that knows both dem and granfe."""

from coupling.locate import PointsOutsideMesh, locate_owned, owner_ranks
from coupling.operators import FieldBasis, NodalProjection, SingularProjection

__all__ = [
    "FieldBasis",
    "NodalProjection",
    "PointsOutsideMesh",
    "SingularProjection",
    "locate_owned",
    "owner_ranks",
]
