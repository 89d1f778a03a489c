"""Load stepping with automatic cut-back, for history-dependent (plastic) problems.

A load path is a parameter ``t`` from 0 to ``t_end`` and a function ``apply(t)`` that sets
the loads (``fem.Constant`` values) for it. Each step is one solve that commits the
quadrature-point state when it converges; a step that fails is halved (the problem has
already restored its last converged fields, and the committed state was never touched),
and steps grow again after easy solves.

Two options of :class:`StepControl` cut the Newton iterations of a plastic path (measured in
``benchmarks/plastic_cost.py``: 5.2x -> 4.3x the elastic path's time at 2.6k dofs, the punch
force the same to 9 digits):

- ``predictor="secant"``: Newton starts from the last two accepted states extrapolated to the
  new load parameter (points unloading start elastic, points in a band plastic) instead of
  from the last accepted state;
- ``load_tol``: Newton converges at ``load_tol`` x the norm of the residual of the new loads on
  the last accepted state (one residual assembly: the size of the load increment), instead of
  the solver's tolerance relative to the step's own first residual, which a good predictor
  makes small, so that it asked for more.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from granfe.solvers import SolveDidNotConverge

__all__ = ["StepControl", "LoadStepFailed", "follow_load_path"]


class LoadStepFailed(RuntimeError):
    """The step was cut below ``min_step`` without converging; the last converged state is kept."""


@dataclass(frozen=True)
class StepControl:
    """first: the first step; min_step: give up below it; max_step: never above it; grow:
    factor after a solve in at most ``easy`` iterations; predictor: ``"last"`` (Newton starts
    from the last accepted state) or ``"secant"`` (from the last two extrapolated); load_tol:
    None (the solver's own tolerances) or the Newton tolerance relative to the load
    increment's residual (module docstring; needs a :class:`granfe.problem.ContinuumProblem`)."""

    first: float
    min_step: float
    max_step: float
    grow: float = 1.5
    easy: int = 6
    predictor: str = "last"
    load_tol: float | None = None

    def __post_init__(self):
        if self.predictor not in ("last", "secant"):
            raise ValueError(f"StepControl.predictor must be 'last' or 'secant', got {self.predictor!r}")
        if self.load_tol is not None and not (np.isfinite(self.load_tol) and 0 < self.load_tol < 1):
            raise ValueError(f"StepControl.load_tol must be in (0, 1) or None, got {self.load_tol!r}")
        if not (0 < self.min_step <= self.first <= self.max_step):
            raise ValueError(f"StepControl needs 0 < min_step <= first <= max_step, got "
                             f"{self.min_step}, {self.first}, {self.max_step}")
        if self.grow < 1:
            raise ValueError(f"StepControl.grow must be >= 1, got {self.grow}")


def follow_load_path(problem, apply: Callable[[float], None], t_end: float,
                     control: StepControl, on_step: Callable[[float, int], None] | None = None,
                     log: Callable[[str], None] | None = None) -> list[tuple[float, int]]:
    """Solve ``problem`` along ``apply(t)`` from its current state to ``t_end``.

    Returns the accepted steps as ``(t, SNES iterations)``; ``on_step(t, its)`` is called
    after each (e.g. to record a reaction). Raises :class:`LoadStepFailed` naming the
    parameter reached when a step below ``control.min_step`` fails.
    """
    t, h, accepted = 0.0, control.first, []
    secant = control.predictor == "secant"
    states = [(0.0, problem.w.x.array.copy())] if secant else []
    while t < t_end * (1 - 1e-12):
        h = min(h, t_end - t)
        apply(t + h)
        try:
            tolerances = None
            # (no load increment, no residual to scale by: the solver's own tolerances)
            increment = problem.residual_norm() if control.load_tol is not None else 0.0
            if increment > 0:
                snes = problem.solver()
                tolerances = snes.getTolerances()
                snes.setTolerances(rtol=0.0, atol=control.load_tol * increment)
            if len(states) == 2:
                (t0, w0), (t1, w1) = states
                problem.w.x.array[:] = w1 + (t + h - t1) / (t1 - t0) * (w1 - w0)
            try:
                its = problem.solve()
            finally:
                if tolerances is not None:
                    snes.setTolerances(*tolerances)
        except (SolveDidNotConverge, FloatingPointError) as err:
            apply(t)
            if h / 2 < control.min_step:
                raise LoadStepFailed(f"no convergence from t = {t:.6g} with a step of "
                                     f"{h:.3g} (min_step {control.min_step:.3g}): {err}") from err
            if log:
                log(f"step {h:.3g} from t = {t:.6g} failed; cut back to {h / 2:.3g}")
            h /= 2
            continue
        t += h
        accepted.append((t, its))
        if secant:
            states = (states + [(t, problem.w.x.array.copy())])[-2:]
        if on_step:
            on_step(t, its)
        if its <= control.easy:
            h = min(h * control.grow, control.max_step)
    return accepted
