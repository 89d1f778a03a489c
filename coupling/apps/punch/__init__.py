"""The bonded punch: a rough punch pushed quasi-statically into bonded grains coupled to the
continuum (``model``: the blocks and the coupled window; ``run``: the scene's run, restart and
size estimate)."""
