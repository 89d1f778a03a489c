"""coupling: bridging-scale DE x FE coupling, the one room that knows both dem and granfe."""
