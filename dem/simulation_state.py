"""`Simulation.state_dict` / `load_state`: a run's exact state as a flat dict of arrays."""

from __future__ import annotations

import numpy as np

__all__ = ["SimulationState"]


_STATE_KEYS = ("x", "v", "omega", "radius", "mass", "inertia", "material", "kind", "force",
               "torque")


def _fit(key, a, shape):
    """A (array-like) checked to have ``shape`` (None: empty) for the state entry ``key``."""
    a = np.asarray(a)
    if (a.size != 0) if shape is None else (a.shape != tuple(shape)):
        raise ValueError(f"state {key!r} has shape {a.shape}, this Simulation needs "
                         f"{'an empty array' if shape is None else tuple(shape)}")
    return a


def _section(d, prefix, exclude=()):
    """The entries of d under ``prefix`` (prefix stripped), but the ``exclude`` names."""
    n = len(prefix)
    return {k[n:]: v for k, v in d.items() if k.startswith(prefix) and k[n:] not in exclude}


class SimulationState:
    """The state API of `dem.integrate.Simulation` (a base of it: the arrays it copies and
    restores are set up by `Simulation.__init__`)."""

    def state_dict(self) -> dict:
        """Everything a run continues from, bit for bit, as a flat dict of copies (numpy
        arrays and Python scalars; ``np.savez``-ready): particles (``particles.*``: x, v,
        omega, force, torque, radius, mass, inertia, material, kind, dim), the force
        parts of the last force pass the next drift books (``integrator.*``), time, step
        count, dt and gravity, the ledger's sums (``ledger.*``), the walls' state
        (``walls.*``), the neighbour list with its contact history and build positions
        (``contacts.*``, `dem.neighbours.NeighbourList.state_dict`), the constant external
        forces of `set_external_force` (``external.rows`` / ``external.force``, empty if
        none: they are in ``particles.force`` already) and the periodic cell (``cell.*``) if
        any. `load_state` restores it into a Simulation built the same way."""
        d = {f"particles.{k}": v for k, v in self.p.state_dict().items()}
        d["particles.dim"] = int(self.p.dim)
        d.update(time=float(self.time), nsteps=int(self.nsteps), dt=float(self.dt),
                 gravity=self.gravity.copy())
        (xg, wp) = self._at
        d.update({"integrator.fe": self._fe.copy(), "integrator.fd": self._fd.copy(),
                  "integrator.td": self._td.copy(), "integrator.hit": self._hit.copy(),
                  "integrator.wall_resultants": self._wf.copy(),
                  "integrator.wall_resultants_prev": self._wf_prev.copy(),
                  "integrator.at_ghosts": np.array(xg), "integrator.at_walls": np.array(wp),
                  "integrator.zeroed": bool(self._zeroed)})
        d.update({f"ledger.{k}": float(v) for k, v in self._led.items()})
        d.update({"ledger.elastic": float(self._elastic), "ledger.spring": float(self._spring),
                  "ledger.initial": float(self._e0), "ledger.initial_shadow": float(self._shadow0)})
        d.update({f"walls.{k}": v for k, v in self.walls.state_dict().items()})
        d.update({f"contacts.{k}": v for k, v in self.nl.state_dict().items()})
        rows, force = self.external_force()
        d.update({"external.rows": np.array(rows, np.int64), "external.force": np.array(force, float)})
        if self.cell is not None:
            d.update({f"cell.{k}": v for k, v in self.cell.state_dict().items()})
            d.update({"cell.bf": self._bf.copy(), "cell.bf_prev": self._bf_prev.copy(),
                      "cell.bf_mixed": self._bf_mixed.copy()})
            if self._xh is not None:
                d.update({"cell.xh_x": self._xh[0].copy(), "cell.xh_h": self._xh[1].copy()})
        return d

    def load_state(self, d) -> None:
        """Restore a `state_dict` (a dict or an ``np.load`` of one) into this Simulation,
        built the same way (particle count, walls, cell). Raises ValueError naming the key
        of a missing entry, an unknown one, or one whose shape does not fit."""
        d = dict(d)
        want = set(self.state_dict())  # the keys of this configuration (cheap: copies)
        # ledger.external, external.*: absent from states written before external forces
        # existed or were kept (such a state leaves the external forces set now as they are)
        optional = {"cell.xh_x", "cell.xh_h", "ledger.external", "external.rows", "external.force"}
        for k in sorted(want - optional):
            if k not in d:
                raise ValueError(f"state has no {k!r} (a state_dict of another configuration?)")
        for k in sorted(d):
            if k not in want | optional:
                raise ValueError(f"state key {k!r} is unknown to this Simulation (a state_dict "
                                 f"of another configuration: cell, walls?)")
        p = self.p
        if int(d["particles.dim"]) != p.dim:
            raise ValueError(f"state 'particles.dim' is {int(d['particles.dim'])}, this "
                             f"Simulation's particles are {p.dim}D")
        fixed = {f"particles.{k}": getattr(p, k) for k in _STATE_KEYS}
        fixed.update({"integrator.fe": self._fe, "integrator.fd": self._fd,
                      "integrator.td": self._td, "integrator.hit": self._hit,
                      "integrator.wall_resultants": self._wf,
                      "integrator.wall_resultants_prev": self._wf_prev,
                      "gravity": self.gravity})
        for k, a in fixed.items():
            _fit(k, d[k], a.shape)
        self.walls.load_state(_section(d, "walls."))
        self.nl.load_state(_section(d, "contacts."))
        for k, a in fixed.items():
            a[...] = np.asarray(d[k], a.dtype)
        self.time, self.nsteps, self.dt = float(d["time"]), int(d["nsteps"]), float(d["dt"])
        ng = len(self._ghost_index())
        xg = _fit("integrator.at_ghosts", d["integrator.at_ghosts"], (ng, 3) if ng else None)
        wp = _fit("integrator.at_walls", d["integrator.at_walls"],
                  (len(self.walls), 3) if len(self.walls) else None)
        self._at = (np.array(xg, float).reshape(-1, 3), np.array(wp, float).reshape(-1, 3))
        self._zeroed = bool(d["integrator.zeroed"])
        for k in self._led:
            self._led[k] = float(d.get(f"ledger.{k}", 0.0))
        self._elastic, self._spring = float(d["ledger.elastic"]), float(d["ledger.spring"])
        self._e0, self._shadow0 = float(d["ledger.initial"]), float(d["ledger.initial_shadow"])
        if self.cell is not None:
            self.cell.load_state(_section(d, "cell.", exclude=("bf", "bf_prev", "bf_mixed",
                                                              "xh_x", "xh_h")))
            self._bf, self._bf_prev, self._bf_mixed = (
                np.array(_fit(f"cell.{k}", d[f"cell.{k}"], (3, 3, 3)), float)
                for k in ("bf", "bf_prev", "bf_mixed"))
            self._xh = (np.array(d["cell.xh_x"], float), np.array(d["cell.xh_h"], float)) \
                if "cell.xh_x" in d else None
        self._ghosts = self._ghost_index()
        self._lay = (None, None)  # the pair layout is rebuilt from the history restored
        self._good = None
        if "external.rows" in d:   # (already in the forces restored: set beside them, not added)
            rows = np.asarray(d["external.rows"], np.int64).ravel()
            f = np.array(_fit("external.force", d["external.force"], (len(rows), 3)), float)
            if len(rows) and (rows.min() < 0 or rows.max() >= p.n):
                raise ValueError(f"state 'external.rows' must lie in [0, {p.n})")
            self._ext = (rows, f, p.x[rows].copy()) if len(rows) else None
        if self._ext is not None:
            self._ext[2][:] = p.x[self._ext[0]]
        self._check()
