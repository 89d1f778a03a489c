"""Load stepping with automatic cut-back, for history-dependent (plastic) problems.

A load path is a parameter ``t`` from 0 to ``t_end`` and a function ``apply(t)`` that sets
the loads (``fem.Constant`` values) for it. Each step is one solve that commits the
quadrature-point state when it converges; a step that fails is halved (the problem has
already restored its last converged fields, and the committed state was never touched),
and steps grow again after easy solves.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from granfe.solvers import SolveDidNotConverge

__all__ = ["StepControl", "LoadStepFailed", "follow_load_path"]


class LoadStepFailed(RuntimeError):
    """The step was cut below ``min_step`` without converging; the last converged state is kept."""


@dataclass(frozen=True)
class StepControl:
    """first: the first step; min_step: give up below it; max_step: never above it; grow:
    factor after a solve in at most ``easy`` iterations."""

    first: float
    min_step: float
    max_step: float
    grow: float = 1.5
    easy: int = 6

    def __post_init__(self):
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
    while t < t_end * (1 - 1e-12):
        h = min(h, t_end - t)
        apply(t + h)
        try:
            its = problem.solve()
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
        if on_step:
            on_step(t, its)
        if its <= control.easy:
            h = min(h * control.grow, control.max_step)
    return accepted
