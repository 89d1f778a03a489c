"""The applications built on the coupling method, one row each in :data:`APPLICATIONS`.

Every command reads this table: the scene loader (its schema and dimensions), ``granfe
check`` (its size estimate and its checks), ``granfe run`` and ``granfe restart`` (its run
function). An application is its own modules plus one row here; nothing else dispatches on
``scene.kind``. Entries name functions as ``"module:attribute"`` and are imported only when
used, so loading a scene imports no finite-element or particle code.

The contract of the named callables:

- ``scene``: a frozen dataclass of scene sections (:mod:`coupling.scene` builds it from TOML);
- ``summarise(scene, ranks) -> dict``: sizes and estimates, with ``memory_estimate_MB_per_rank``
  and ``memory_driver`` (the scene key that drives memory);
- ``checks(scene, info) -> list[str]``: warnings; raise :class:`coupling.scene.SceneError`
  naming the key for what the run would refuse;
- ``run(scene, out, comm, *, progress, checkpoint, stop, meta)``: run into ``out`` (continue
  from ``checkpoint`` when given), poll ``stop`` once per step;
- ``restart_mutable``: the scene keys a restart may change.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

__all__ = ["Application", "APPLICATIONS", "application", "summarise"]


@dataclass(frozen=True)
class Application:
    """One application: its scene kind, dimensions and callables (``"module:attribute"``)."""

    kind: str
    dimensions: tuple[int, ...]
    default_name: str
    scene: str
    summarise: str
    run: str
    checks: str | None = None
    #: ``section.key`` prefixes a restart may change (outside the run's fingerprint)
    restart_mutable: tuple[str, ...] = ("scene.name", "output.")

    def load(self, role: str):
        """The object named by ``role`` (``"scene"``, ``"summarise"``, ``"run"``, ``"checks"``)."""
        target = getattr(self, role)
        if target is None:
            return None
        module, _, attr = target.partition(":")
        return getattr(importlib.import_module(module), attr)


APPLICATIONS: dict[str, Application] = {
    "bonded_punch": Application(
        kind="bonded_punch", dimensions=(2,), default_name="scene",
        scene="coupling.apps.punch.scene:Scene", summarise="coupling.apps.punch.run:summarise_punch",
        run="coupling.apps.punch.run:execute",
        restart_mutable=("scene.name", "output.", "solver.", "penetrator.steps")),
    "penetration": Application(
        kind="penetration", dimensions=(2, 3), default_name="cpt_2d",
        scene="coupling.apps.penetration.scene:PenetrationScene",
        summarise="coupling.apps.penetration.run:summarise_penetration",
        run="coupling.apps.penetration.run:execute", checks="coupling.apps.penetration.run:penetration_checks"),
}


def application(kind: str) -> Application:
    """The application of a scene kind; ``ValueError`` naming ``scene.kind`` otherwise."""
    try:
        return APPLICATIONS[kind]
    except KeyError:
        raise ValueError(f"scene.kind must be one of {list(APPLICATIONS)}, got {kind!r}") from None


def summarise(scene, ranks: int = 1) -> dict:
    """Sizes and cost estimates of ``scene`` on ``ranks`` MPI ranks, without building FE
    objects (for ``granfe check``; :func:`coupling.preflight.preflight` adds the checks)."""
    return application(scene.scene.kind).load("summarise")(scene, ranks)
