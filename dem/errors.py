"""Named errors of the DEM engine, so callers can catch each failure mode on its own."""

from __future__ import annotations

__all__ = ["BlowUpError", "DemError", "DomainError", "MaterialError", "OverlapError",
           "TimeStepError"]


class DemError(Exception):
    """Base class of all `dem` errors."""


class MaterialError(DemError, ValueError):
    """A contact material parameter is outside its physical range."""


class OverlapError(DemError, ValueError):
    """Particles overlap at the start of a run (count and largest overlap in the message)."""


class TimeStepError(DemError, ValueError):
    """The requested time step is above the critical one (pass ``force_dt=True`` to insist)."""


class DomainError(DemError, RuntimeError):
    """A particle left the user-given domain box."""


class BlowUpError(DemError, FloatingPointError):
    """NaN or a kinetic-energy jump; the last good state was written to ``self.path``."""

    def __init__(self, message: str, path: str | None = None):
        super().__init__(message)
        self.path = path
