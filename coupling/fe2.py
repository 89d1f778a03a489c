"""Two-scale FE x DEM (FE^2, seed 004 §2.1.3, Fig. 3): one RVE of grains per quadrature point.

The macro problem is a :class:`~granfe.problem.ContinuumProblem` of the
:class:`~granfe.models.quadrature_stress.QuadratureStress` model; every quadrature point of
an owned cell holds a `dem.rve.RVE` (so the RVEs are distributed over the ranks with the
cells that own them, and no RVE is ever copied between ranks). Localisation / homogenisation
(seed 004 eq. 19, 23): the macro strain of a point goes down to its RVE as a strain
increment from the committed state, the relaxed Love-Weber stress comes back up.

Macro solve: PETSc SNES (``newtonls``, no line search) through
``dolfinx.fem.petsc.NonlinearProblem``, whose residual callback first drives every RVE to the
strain of the iterate (each from its committed state: the response of a step does not depend
on the iterations that led to it), fills the stress at the points, then assembles. The
Jacobian is the model's, assembled from the tangent C filled at the points
(:class:`MacroNewton`): the perturbation tangent `RVE.tangent` at the committed state (a
modified Newton; its strain probes of 1e-5 stay elastic, so once the contacts slide it is
far stiffer than the secant of a step and the iteration converges linearly: 4, 7, 10, 19,
21, 21 iterations over the first six steps of 5e-4 of ``demos/2d/fe2_biaxial.py``, q/p 0.10
-> 0.28),
the affine estimate `RVE.affine_stiffness`, or ``"secant"``: that tangent corrected at every
point after every evaluation by a rank-one (Broyden) update to the secant of its last two
evaluations, kept from step to step (a quasi-Newton at the material points, no extra
relaxation: 3-6 iterations a step over eight such steps of the 16-point biaxial test of
``tests/coupling/test_fe2.py``). :attr:`FE2.history` keeps the
residual norms of every solve. Converged when the residual is below ``force_tol`` x the norm
of the internal forces of the stress (the RVE stresses are only as good as their relaxation,
``QuasiStatic.force_tol``: the macro tolerance must stay above that noise).

Load stepping with cut-back: :meth:`FE2.solve` is one load step with the contract of
:func:`granfe.stepping.follow_load_path` (commit on success; on failure every RVE and the
filled points are restored and SolveDidNotConverge raised, so the step is halved). An RVE
that fails to relax (`dem.rve.ConvergenceError`) fails the macro iteration (NaN residual).

Checkpoint: :meth:`FE2.state_dict` holds the problem's state and every RVE's
``state_dict`` keyed by the point's global number; one ``.npz`` a rank, written atomically
with a manifest (:mod:`coupling.checkpoints`), so a kill mid-write keeps the last one.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import assemble_residual, assemble_vector, assign
from dolfinx.io import VTXWriter

from coupling.checkpoints import CheckpointError, find_checkpoint, write_checkpoint
from dem.integrate import Simulation
from dem.periodic import PeriodicCell
from dem.rve import RVE, ConvergenceError, from_mandel, to_mandel
from dem.state import Particles
from granfe.io import ContinuumWriter
from granfe.models.quadrature_stress import QuadratureStress, fill
from granfe.problem import ContinuumProblem
from granfe.solvers import SolveDidNotConverge
from granfe.stepping import StepControl, follow_load_path

__all__ = ["FE2", "FE2Writer", "MacroNewton", "clone_rve"]

TANGENTS = ("perturbation", "affine", "initial", "secant")


@dataclass(frozen=True)
class MacroNewton:
    """Settings of the macro solve.

    force_tol: residual norm over the norm of the internal forces of the filled stress, in
    (0, 1); max_it: Newton iterations of a load step (>= 1); tangent: ``"perturbation"``
    (`RVE.tangent` at the committed state of every point, every ``tangent_every`` steps),
    ``"affine"`` (`RVE.affine_stiffness`, an upper bound: safe, slower) or ``"initial"``
    (the perturbation tangent of the first step, kept) or ``"secant"`` (the perturbation
    tangent every ``tangent_every`` steps, corrected at every point after every evaluation by
    the rank-one (Broyden) update that makes it the secant of the last two evaluations:
    ``C += (dS - C dE) dE^T / dE.dE``, skipped when ``|dE| < secant_min``; a
    quasi-Newton at the material points, no extra relaxation); tangent_delta: perturbation
    strain, in (0, 1e-2); tangent_every: load steps between perturbation tangents (>= 1);
    secant_min: smallest strain change of a secant update (>= 0; below it the difference of
    two relaxed stresses is mostly their relaxation error).
    """

    force_tol: float = 1e-3
    max_it: int = 30
    tangent: str = "perturbation"
    tangent_delta: float = 1e-5
    tangent_every: int = 1
    secant_min: float = 1e-6

    def __post_init__(self):
        checks = (("force_tol", 0 < self.force_tol < 1, "in (0, 1)"),
                  ("max_it", isinstance(self.max_it, int) and self.max_it >= 1, "an integer >= 1"),
                  ("tangent", self.tangent in TANGENTS, f"one of {TANGENTS}"),
                  ("tangent_delta", 0 < self.tangent_delta < 1e-2, "in (0, 1e-2)"),
                  ("tangent_every", isinstance(self.tangent_every, int) and self.tangent_every >= 1,
                   "an integer >= 1"),
                  ("secant_min", self.secant_min >= 0, ">= 0"))
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"MacroNewton.{name} must be {rule}, got {getattr(self, name)!r}")


def clone_rve(rve: RVE) -> RVE:
    """An independent RVE in ``rve``'s state (the same grains, contacts and committed state),
    built through the public state API."""
    state = rve.state_dict()
    grains = {k[len("particles."):]: v for k, v in state.items() if k.startswith("particles.")}
    dim = rve.dim
    sim = Simulation(Particles.from_state_dict(grains), rve.sim.materials,
                     cell=PeriodicCell(np.asarray(state["cell.h"])[:dim, :dim]),
                     allow_overlap=True)
    out = RVE(sim, rve.solver)
    out.load_state(state)
    out.commit()
    return out


class FE2:
    """Macro problem with one RVE per owned quadrature point (see the module docstring).

    Args:
        problem: a ContinuumProblem of the QuadratureStress model, with its conditions set
            (loads as ``fem.Constant`` for load stepping).
        prototypes: consolidated RVEs (their committed state is the initial one of the
            points; the same dimension as the mesh). Never modified: every point gets a clone.
        pick: ``pick(global_point) -> index`` into ``prototypes`` (default: ``global_point %
            len(prototypes)``); global_point = original cell index x points a cell + point,
            independent of the partition, so any rank count builds the same RVEs.
        settings: :class:`MacroNewton`.
        log: called with progress lines (on rank 0).
    """

    def __init__(self, problem: ContinuumProblem, prototypes: Sequence[RVE],
                 pick: Callable[[int], int] | None = None, settings: MacroNewton | None = None,
                 log: Callable[[str], None] | None = None):
        if not isinstance(problem.model, QuadratureStress):
            raise TypeError(f"FE2 needs a problem of the quadrature_stress model, got "
                            f"{problem.model.name!r}")
        if not prototypes or any(r.dim != problem.gdim for r in prototypes):
            raise ValueError(f"FE2: give RVEs of the mesh's dimension {problem.gdim}")
        self.problem, self.settings = problem, settings or MacroNewton()
        self.comm = problem.domain.comm
        self._log = log if self.comm.rank == 0 else None
        state = problem.state
        Q = state.committed["stress"].function_space
        self.k = Q.dofmap.index_map_bs
        self.n = Q.dofmap.index_map.size_local  # owned points
        cells = np.arange(problem.domain.topology.index_map(problem.gdim).size_local, dtype=np.int32)
        dofs = Q.dofmap.list[cells]
        self.per_cell = dofs.shape[1]
        self.point_cell = np.empty(self.n, np.int32)
        self.point_cell[dofs.ravel()] = np.repeat(cells, self.per_cell)
        original = np.asarray(problem.domain.topology.original_cell_index)[self.point_cell]
        local_q = np.empty(self.n, np.int64)
        local_q[dofs.ravel()] = np.tile(np.arange(self.per_cell), len(cells))
        self.global_point = original.astype(np.int64) * self.per_cell + local_q
        pick = pick or (lambda g: g % len(prototypes))
        self.rves = [clone_rve(prototypes[pick(int(g))]) for g in self.global_point]
        self._strain_q = fem.Function(Q)
        self._strain_expr = fem.Expression(problem.model.strain(problem.split(problem.w)[0]),
                                           Q.element.interpolation_points,
                                           jit_options=problem.jit_options)
        self._S = np.array([to_mandel(r.stress(), r.dim) for r in self.rves]).reshape(self.n, self.k)
        self._E = np.zeros((self.n, self.k))
        self._S_c, self._E_c = self._S.copy(), self._E.copy()
        self._moved = np.zeros(self.n, bool)
        self._C = np.zeros((self.n, self.k, self.k))
        self._C_start = self._C.copy()
        self._S_prev, self._E_prev = self._S_c.copy(), self._E_c.copy()
        self._fill_points()
        self.steps_done, self.history, self.log_rows = 0, [], []
        self.stats = dict(rve_evaluations=0, rve_steps=0, rve_seconds=0.0, tangent_seconds=0.0,
                          failures=0)
        self._nlp, self._failed, self._f_ref = None, False, 1.0

    # ------------------------------------------------------------------ points
    def _fill_points(self) -> None:
        st = self.problem.state
        fill(st, "stress", self._S)
        fill(st, "strain", self._E)
        fill(st, "tangent", self._C)

    def _evaluate(self) -> bool:
        """Every owned RVE at the strain of the current fields (from its committed state);
        False if one did not relax. Not collective (the fill after it is)."""
        self._strain_q.interpolate(self._strain_expr)
        self._E = self._strain_q.x.array[: self.n * self.k].reshape(self.n, self.k).copy()
        ok, t0 = True, time.perf_counter()
        for i, rve in enumerate(self.rves):
            de = self._E[i] - self._E_c[i]
            if self._moved[i]:
                rve.restore()
                self._moved[i] = False
            if not de.any():
                self._S[i] = self._S_c[i]
                continue
            try:
                self._moved[i] = True
                info = rve.load(strain_increment=from_mandel(de, rve.dim))
            except ConvergenceError:
                ok = False
                break
            self._S[i] = to_mandel(info["stress"], rve.dim)
            if self.settings.tangent == "secant":
                self._secant(i)
            self.stats["rve_evaluations"] += 1
            self.stats["rve_steps"] += info["steps"]
        self.stats["rve_seconds"] += time.perf_counter() - t0
        return ok

    def _secant(self, i: int) -> None:
        """Broyden update of point i's tangent from its last evaluation to this one."""
        de = self._E[i] - self._E_prev[i]
        dd = float(de @ de)
        if dd > self.settings.secant_min**2:
            c = self._C[i]
            c += np.outer(self._S[i] - self._S_prev[i] - c @ de, de) / dd
            self._S_prev[i], self._E_prev[i] = self._S[i], self._E[i]

    def _tangents(self) -> None:
        """Fill C at the committed state of every point (module docstring)."""
        s, t0 = self.settings, time.perf_counter()
        self._S_prev, self._E_prev = self._S_c.copy(), self._E_c.copy()
        if s.tangent == "initial" and self.steps_done > 0:
            return
        if self.steps_done % s.tangent_every and s.tangent != "initial":
            return
        for i, rve in enumerate(self.rves):
            if self._moved[i]:
                rve.restore()
                self._moved[i] = False
            self._C[i] = (rve.affine_stiffness() if s.tangent == "affine"
                          else rve.tangent(delta=s.tangent_delta))
        fill(self.problem.state, "tangent", self._C)
        self.stats["tangent_seconds"] += time.perf_counter() - t0

    # ------------------------------------------------------------------ SNES
    def _residual(self, snes, x, b, ctx):
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        assign(x, self.problem.w)
        ok = self.comm.allreduce(int(self._evaluate()), MPI.MIN)
        st = self.problem.state
        fill(st, "stress", self._S)
        fill(st, "strain", self._E)
        if self.settings.tangent == "secant":
            fill(st, "tangent", self._C)
        if not ok:
            self._failed = True
            b.set(np.nan)
            return
        assemble_residual(snes, x, b, **ctx)

    def _converged(self, snes, it, norms):
        _, _, fnorm = norms
        self.history[-1].append(float(fnorm))
        if not np.isfinite(fnorm):
            return PETSc.SNES.ConvergedReason.DIVERGED_FNORM_NAN
        if fnorm <= self.settings.force_tol * self._f_ref:
            return PETSc.SNES.ConvergedReason.CONVERGED_FNORM_ABS
        if it >= self.settings.max_it:
            return PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
        return PETSc.SNES.ConvergedReason.ITERATING

    def _build(self) -> None:
        p = self.problem
        self._nlp = nlp = p.snes_problem(p.residual(), p.prefix)
        ctx = {"u": p.w, "residual": nlp.F, "jacobian": nlp.J, "bcs": p.bcs}
        nlp.solver.setFunction(self._residual, nlp.b, kargs={"ctx": ctx})
        nlp.solver.setConvergenceTest(self._converged)
        model = p.model
        v = ufl.TestFunction(p.V)
        self._internal = fem.form(ufl.dot(p.state.committed["stress"],
                                          model.strain(p.split(v)[0])) * p.dx,
                                  jit_options=p.jit_options)

    def _force_scale(self) -> float:
        """Norm of the nodal internal forces of the filled stress (every dof, reactions too)."""
        vec = assemble_vector(self._internal)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        norm = vec.norm()
        vec.destroy()
        return norm if norm > 0 else 1.0

    # ------------------------------------------------------------------ steps
    def solve(self) -> int:
        """One load step at the conditions set now: SNES iterations; commits every RVE, or
        restores every one and raises SolveDidNotConverge (the step may be cut back)."""
        if self._nlp is None:
            self._build()
        t0 = time.perf_counter()
        try:
            self._tangents()
        except ConvergenceError as err:
            self._restore()
            raise SolveDidNotConverge(f"FE2 tangent: {err}", 0) from err
        self._C_start = self._C.copy()
        self._f_ref = self._force_scale()
        self.history.append([])
        self._failed = False
        self._nlp.solve()
        try:
            its = self.problem.checked(self._nlp, "FE2 macro step")
        except (SolveDidNotConverge, FloatingPointError):
            self._restore()
            raise
        for i, rve in enumerate(self.rves):
            if self._moved[i]:
                rve.commit()
            self._moved[i] = False
        self._S_c, self._E_c = self._S.copy(), self._E.copy()
        self.steps_done += 1
        row = dict(step=self.steps_done, iterations=its, residuals=self.history[-1],
                   seconds=time.perf_counter() - t0)
        self.log_rows.append(row)
        if self._log:
            self._log(f"FE2 step {self.steps_done}: {its} iterations, |R|/|f| "
                      + " ".join(f"{r / self._f_ref:.1e}" for r in self.history[-1])
                      + f", {row['seconds']:.1f} s")
        return its

    def _restore(self) -> None:
        self.stats["failures"] += 1
        for i, rve in enumerate(self.rves):
            if self._moved[i]:
                rve.restore()
            self._moved[i] = False
        self._S, self._E = self._S_c.copy(), self._E_c.copy()
        self._C = self._C_start.copy()
        self._fill_points()

    def follow(self, apply: Callable[[float], None], t_end: float, control: StepControl,
               on_step: Callable[[float, int], None] | None = None):
        """:func:`granfe.stepping.follow_load_path` over this two-scale problem."""
        return follow_load_path(self, apply, t_end, control, on_step=on_step, log=self._log)

    # ------------------------------------------------------------------ measures
    def stress(self) -> np.ndarray:
        """(owned points, k) committed Mandel stresses [Pa]."""
        return self._S_c.copy()

    def strain(self) -> np.ndarray:
        """(owned points, k) committed Mandel strains."""
        return self._E_c.copy()

    def per_point(self, measure: Callable[[RVE], float]) -> np.ndarray:
        """``measure(rve)`` of every owned point (e.g. ``RVE.coordination``)."""
        return np.array([measure(r) for r in self.rves])

    def gather(self, values: np.ndarray) -> np.ndarray | None:
        """Owned-point values of every rank in global point order, on rank 0 (None
        elsewhere). Collective."""
        parts = self.comm.gather((self.global_point, np.asarray(values)), root=0)
        if self.comm.rank != 0:
            return None
        g = np.concatenate([p[0] for p in parts])
        v = np.concatenate([p[1] for p in parts])
        return v[np.argsort(g)]

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """This rank's problem state (``problem/...``), committed points (``points/...``) and
        every RVE's committed state (``rve/<global point>/...``)."""
        out = {f"problem/{k}": v for k, v in self.problem.state_dict().items()}
        out.update({"points/global": self.global_point, "points/stress": self._S_c,
                    "points/strain": self._E_c, "points/tangent": self._C,
                    "points/steps_done": np.int64(self.steps_done)})
        for g, rve in zip(self.global_point, self.rves, strict=True):
            rve.restore()
            out.update({f"rve/{g}/{k}": v for k, v in rve.state_dict().items()})
        self._moved[:] = False
        return out

    def load_state(self, d) -> None:
        """Restore :meth:`state_dict` output of the same mesh and partition."""
        if not np.array_equal(np.asarray(d["points/global"]), self.global_point):
            raise ValueError("FE2.load_state: the saved points are not this rank's (another "
                             "mesh or rank count?)")
        self.problem.load_state({k[len("problem/"):]: v for k, v in d.items()
                                 if k.startswith("problem/")})
        for g, rve in zip(self.global_point, self.rves, strict=True):
            head = f"rve/{g}/"
            rve.load_state({k[len(head):]: v for k, v in d.items() if k.startswith(head)})
            rve.commit()
        self._S_c = np.array(d["points/stress"]).reshape(self.n, self.k)
        self._E_c = np.array(d["points/strain"]).reshape(self.n, self.k)
        self._C = np.array(d["points/tangent"]).reshape(self.n, self.k, self.k)
        self._S, self._E = self._S_c.copy(), self._E_c.copy()
        self.steps_done = int(d["points/steps_done"])
        self._moved[:] = False
        self._fill_points()

    def write_checkpoint(self, directory: str | Path) -> Path:
        """:meth:`state_dict` of every rank (``fe2_rank<r>_of<n>.npz``) as the checkpoint
        ``directory``, written atomically (:func:`coupling.checkpoints.write_checkpoint`:
        sha256 manifest, the previous checkpoint kept as ``<directory>.prev`` until the new
        one is in place). Collective."""
        comm = self.comm

        def files(tmp: Path) -> list[str]:
            name = f"fe2_rank{comm.rank}_of{comm.size}.npz"
            np.savez(tmp / name, **self.state_dict())
            return [name]

        return write_checkpoint(directory, self.steps_done, comm, files, meta={"kind": "fe2"})

    def read_checkpoint(self, directory: str | Path) -> list[str]:
        """Continue from the newest valid checkpoint among ``directory``, its unfinished
        ``.tmp-*`` and ``.prev`` (:func:`coupling.checkpoints.find_checkpoint`); returns the
        notes on those passed over (a truncated file, a missing manifest). Collective;
        raises :class:`coupling.checkpoints.CheckpointError` when none is valid or it was
        written on another rank count."""
        comm = self.comm
        found = None
        if comm.rank == 0:
            try:
                found = find_checkpoint(directory)
            except CheckpointError as err:
                found = err
        found = comm.bcast(found, root=0)
        if isinstance(found, CheckpointError):
            raise found
        path, manifest, notes = found
        if manifest.get("ranks") != comm.size:
            raise CheckpointError(f"the checkpoint {path} was written on {manifest.get('ranks')} "
                                  f"ranks; this run has {comm.size} (the RVEs are stored by owner)")
        with np.load(Path(path) / f"fe2_rank{comm.rank}_of{comm.size}.npz") as data:
            self.load_state({k: data[k] for k in data.files})
        return notes


class FE2Writer:
    """VTX series of an FE2 run: the continuum's (``<name>_fields.bp``, ``_stress.bp``,
    ``_state.bp``, see `granfe.io.ContinuumWriter`) plus ``<name>_rve.bp``: per cell the mean
    coordination number (contacts a grain) and solid fraction of its RVEs (DG0)."""

    def __init__(self, fe2: FE2, out_dir: str | Path, name: str = "fe2"):
        self.fe2 = fe2
        self.continuum = ContinuumWriter(fe2.problem, out_dir, name)
        S = fem.functionspace(fe2.problem.domain, ("Discontinuous Lagrange", 0))
        self.rve = {n: fem.Function(S, name=n) for n in ("coordination", "solid_fraction")}
        self.n_cells = fe2.problem.domain.topology.index_map(fe2.problem.gdim).size_local
        self.path = Path(out_dir) / f"{name}_rve.bp"
        self._writer = VTXWriter(fe2.problem.domain.comm, self.path, list(self.rve.values()),
                                 engine="BP4")

    def write(self, t: float) -> None:
        f = self.fe2
        for name, measure in (("coordination", RVE.coordination),
                              ("solid_fraction", RVE.solid_fraction)):
            values = f.per_point(measure)
            dofs = self.rve[name].function_space.dofmap.list[:, 0]
            cell_mean = np.zeros(self.n_cells)
            np.add.at(cell_mean, f.point_cell, values / f.per_cell)
            self.rve[name].x.array[dofs[: self.n_cells]] = cell_mean
            self.rve[name].x.scatter_forward()
        self.continuum.write(t)
        self._writer.write(t)

    def close(self) -> None:
        self.continuum.close()
        self._writer.close()
