"""Which numba threading layer the parallel kernels use (imported first by `dem`).

OpenMP before TBB: a parallel region costs ~1.5 us under GNU OpenMP and ~11 us under TBB on
the project's 2-vCPU VM (median of 2000 back-to-back launches), and a DEM step opens up to
four; the layer is picked at the first parallel launch, so this must run before it. An
explicit ``NUMBA_THREADING_LAYER`` or ``NUMBA_THREADING_LAYER_PRIORITY`` is left alone.
"""

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ and \
        "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
