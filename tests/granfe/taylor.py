"""Taylor test of a problem's consistent tangent at its current state, shared by the
plasticity tests: the remainder |F(w + h dw) - F(w) - h J dw| of a random direction dw must
fall like h^2 (like h with a wrong tangent)."""

import numpy as np
import ufl
from dolfinx import fem


def taylor_rates(p, scale: float = 1e-4, steps=(1e-2, 5e-3, 2.5e-3, 1.25e-3), seed: int = 0) -> np.ndarray:
    """Convergence rates of the Taylor remainder of ``p.residual()`` (a ContinuumProblem)
    about ``p.w`` along a random direction of size ``scale``; ``p.w`` is left as it was."""
    F = p.residual()
    J = ufl.derivative(F, p.w)
    rng = np.random.default_rng(seed)
    dw = fem.Function(p.V)
    dw.x.array[:] = rng.standard_normal(dw.x.array.size) * scale
    dw.x.scatter_forward()
    Fc, Jdw = fem.form(F), fem.form(ufl.action(J, dw))
    w0 = p.w.x.array.copy()

    def residual():
        return fem.assemble_vector(Fc).array.copy()

    R0, JdW = residual(), fem.assemble_vector(Jdw).array.copy()
    remainders = []
    for h in steps:
        p.w.x.array[:] = w0 + h * dw.x.array
        remainders.append(np.linalg.norm(residual() - R0 - h * JdW))
    p.w.x.array[:] = w0
    return np.log2(np.array(remainders[:-1]) / remainders[1:])
