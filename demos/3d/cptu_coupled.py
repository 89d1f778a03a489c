"""Saturated coupled cone penetration in 3D (CPTu): the pore pressure round the cone (u1 on
its face, u2 at the shoulder) and q_c against depth, dry, drained and at two push rates, on
``scenes/cptu_3d.toml``.

The runs, readings, outputs and checks are those of demos/2d/cptu_coupled.py (its docstring
says what each shows), which this runs on the 3D scene: a loose window of ~5400 Hertz-Mindlin
spheres round a cone of 8 grain diameters in a cylindrical micropolar chamber, one Darcy pore
pressure over the whole chamber (`coupling.apps.penetration.saturated`), u1 and u2 read at
four azimuths, q_u the pore pressure's push on the cone over pi R^2; the continuum drained
(the Biot continuum is 2D so far). The scene's permeability (1.5e-10 m^2, V ~ 0.075) is the two
rates'; drained 100x it. No undrained run by default: the pressure shares the continuum's
mesh, the cone is about one element wide, and undrained its error outgrows the soil's
stresses (the 2D demo's comment has the figures; ``--runs undrained`` runs it). Any option of
the 2D demo can be given (``--runs``, ``--every``, ``--out``, ...).

Run: ``NUMBA_NUM_THREADS=1 python demos/3d/cptu_coupled.py`` (one core, ~8 min);
``GRANFE_SHORT=1``: a small window (~2000 spheres round a cone of 2.5 grain radii, 16 mm of
push), dry, drained and V ~ 0.08, ~1.5 min.
"""

import runpy
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULTS = ["--scene", str(REPO / "scenes" / "cptu_3d.toml"), "--out", "output/cptu_coupled_3d"]
sys.argv = [sys.argv[0], *DEFAULTS, *sys.argv[1:]]   # (the options given after win)
runpy.run_path(str(REPO / "demos" / "2d" / "cptu_coupled.py"), run_name="__main__")
