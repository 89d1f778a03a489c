"""Cone and pile penetration into frictional grains coupled to the continuum (``coupled``: the
coupled and full-DEM penetrations; ``penetrators``: the cone and pile clumps;
``moving_window``: the DE window that follows the tip; ``run``: the scene's run, outputs,
checkpoints and size estimate)."""
