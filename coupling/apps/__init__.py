"""The applications built on the bridging-scale method, one package each (``punch``: a
rough punch into bonded grains; ``penetration``: cone and pile penetration with the window
that follows the tip). Each is registered by one row in :mod:`coupling.applications`."""
