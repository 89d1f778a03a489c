"""Two-scale FE x DEM (FE^2, seed 004 §2.1.3, Fig. 3): one RVE of grains per quadrature point.

The macro problem is a :class:`~granfe.problem.ContinuumProblem` of the
:class:`~granfe.models.quadrature_stress.QuadratureStress` model; every quadrature point of
an owned cell has a `dem.rve.RVE`, at first on the rank owning the cell; after a load step
RVEs move between ranks to even the ranks' work of the step (:mod:`coupling.fe2_placement`:
a Newton iteration waits for the slowest rank), their strains sent to them and their
stresses back at every iteration (a few numbers a point). Localisation / homogenisation
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
from coupling.fe2_placement import Placement, balance
from dem.integrate import Simulation
from dem.periodic import PeriodicCell
from dem.rve import RVE, ConvergenceError, from_mandel, to_mandel
from dem.state import Particles
from granfe.io import ContinuumWriter
from granfe.models.quadrature_stress import QuadratureStress, fill
from granfe.problem import ContinuumProblem
from granfe.solvers import SolveDidNotConverge
from granfe.stepping import StepControl, follow_load_path

__all__ = ["FE2", "FE2Writer", "MacroNewton", "clone_rve", "consolidate_shared",
           "rve_from_state"]

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
    two relaxed stresses is mostly their relaxation error); imbalance: after a load step,
    RVEs move between ranks (:mod:`coupling.fe2_placement`) while the most and the least
    loaded rank's RVE work of the step differ by more than this fraction of the mean (>= 0;
    ``math.inf``: every RVE stays with its cell).
    """

    force_tol: float = 1e-3
    max_it: int = 30
    tangent: str = "perturbation"
    tangent_delta: float = 1e-5
    tangent_every: int = 1
    secant_min: float = 1e-6
    imbalance: float = 0.05

    def __post_init__(self):
        checks = (("force_tol", 0 < self.force_tol < 1, "in (0, 1)"),
                  ("max_it", isinstance(self.max_it, int) and self.max_it >= 1, "an integer >= 1"),
                  ("tangent", self.tangent in TANGENTS, f"one of {TANGENTS}"),
                  ("tangent_delta", 0 < self.tangent_delta < 1e-2, "in (0, 1e-2)"),
                  ("tangent_every", isinstance(self.tangent_every, int) and self.tangent_every >= 1,
                   "an integer >= 1"),
                  ("secant_min", self.secant_min >= 0, ">= 0"),
                  ("imbalance", self.imbalance >= 0, ">= 0"))
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f"MacroNewton.{name} must be {rule}, got {getattr(self, name)!r}")


def clone_rve(rve: RVE) -> RVE:
    """An independent RVE in ``rve``'s state (the same grains, contacts and committed state),
    built through the public state API."""
    return rve_from_state(rve.state_dict(), rve.sim.materials, rve.solver)


def rve_from_state(state: dict, materials, solver) -> RVE:
    """An RVE built from an `RVE.state_dict` (committed there; continues it bit for bit),
    with the Simulation's ``materials`` and the `QuasiStatic` ``solver``."""
    grains = {k[len("particles."):]: v for k, v in state.items() if k.startswith("particles.")}
    dim = int(state["particles.dim"])
    sim = Simulation(Particles.from_state_dict(grains), materials,
                     cell=PeriodicCell(np.asarray(state["cell.h"])[:dim, :dim]),
                     allow_overlap=True)
    out = RVE(sim, solver)
    out.load_state(state)
    out.commit()
    return out


def consolidate_shared(comm: MPI.Comm, makers: Sequence[Callable[[], RVE]]) -> list[RVE]:
    """``[make() for make in makers]`` on every rank, each made once: rank r runs the makers
    r, r + size, ... and broadcasts their states, from which every other rank builds the same
    RVE (`rve_from_state`: the same bits as if it had made it). Collective. (Every rank making
    every prototype is work the second rank cannot share: seconds a packing.)"""
    mine = {i: make() for i, make in enumerate(makers) if i % comm.size == comm.rank}
    out = []
    for i in range(len(makers)):
        rve = mine.get(i)
        sent = comm.bcast(None if rve is None else
                          (rve.state_dict(), rve.sim.materials, rve.solver), root=i % comm.size)
        out.append(rve if rve is not None else rve_from_state(*sent))
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
        self._prototypes = list(prototypes)
        self._pick = pick or (lambda g: g % len(prototypes))
        self.placement = Placement(self.comm, self.global_point)
        self.held = {int(g): clone_rve(self._prototype(g)) for g in self.global_point}
        self._moved: set[int] = set()  # held points whose RVE left its committed state
        self._cost: dict[int, float] = {}  # held points' particle-steps in this load step
        self._strain_q = fem.Function(Q)
        self._strain_expr = fem.Expression(problem.model.strain(problem.split(problem.w)[0]),
                                           Q.element.interpolation_points,
                                           jit_options=problem.jit_options)
        self._S = np.array([to_mandel(self.held[int(g)].stress(), problem.gdim)
                            for g in self.global_point]).reshape(self.n, self.k)
        self._E = np.zeros((self.n, self.k))
        self._S_c, self._E_c = self._S.copy(), self._E.copy()
        self._C = np.zeros((self.n, self.k, self.k))
        self._C_start = self._C.copy()
        self._S_prev, self._E_prev = self._S_c.copy(), self._E_c.copy()
        self._fill_points()
        self.steps_done, self.history, self.log_rows = 0, [], []
        self.stats = dict(rve_evaluations=0, rve_steps=0, rve_seconds=0.0, tangent_seconds=0.0,
                          wait_seconds=0.0, step_seconds=0.0, failures=0, moves=0,
                          rve_steps_max=0)
        self._nlp, self._failed, self._f_ref = None, False, 1.0

    # ------------------------------------------------------------------ points
    def _fill_points(self) -> None:
        st = self.problem.state
        fill(st, "stress", self._S)
        fill(st, "strain", self._E)
        fill(st, "tangent", self._C)

    @property
    def rves(self) -> list[RVE]:
        """The RVEs this rank holds (ascending global point; not necessarily its own points'
        after a rebalance)."""
        return [self.held[g] for g in sorted(self.held)]

    def _prototype(self, g: int) -> RVE:
        return self._prototypes[self._pick(int(g))]

    def _fresh(self, g: int) -> RVE:
        """Held point g's RVE at its committed state."""
        rve = self.held[g]
        if g in self._moved:
            rve.restore()
            self._moved.discard(g)
        return rve

    def _exchange(self, tasks: dict, work: Callable[[int, RVE, object], object]) -> dict:
        """``work(g, rve, task)`` for the tasks ``{point: task}`` given at the homes, run by the
        points' workers in ascending point order (deterministic), the answers back at the
        homes; the time waiting for them (the other ranks' work) is booked as wait_seconds.
        Collective."""
        todo = self.placement.to_workers(tasks)
        done = {}
        for g in sorted(todo):
            done[g] = work(g, self._fresh(g), todo[g])
            if done[g] is None:
                break  # an RVE failed: the iteration is lost, the rest need not run
        t0 = time.perf_counter()
        self.comm.barrier()
        self.stats["wait_seconds"] += time.perf_counter() - t0
        return self.placement.to_homes(done)

    def _relax(self, g: int, rve: RVE, de):
        """Worker side of an evaluation: (Mandel stress or None if de = 0, DEM steps), or None
        if the RVE did not relax."""
        if not de.any():
            return (None, 0)
        t0 = time.perf_counter()
        self._moved.add(g)
        try:
            info = rve.load(strain_increment=from_mandel(de, rve.dim))
        except ConvergenceError:
            return None
        finally:
            self.stats["rve_seconds"] += time.perf_counter() - t0
        self._cost[g] = self._cost.get(g, 0.0) + info["steps"] * rve.sim.p.n
        self.stats["rve_evaluations"] += 1
        self.stats["rve_steps"] += info["steps"]
        self.stats["rve_steps_max"] = max(self.stats["rve_steps_max"], info["steps"])
        return (to_mandel(info["stress"], rve.dim), info["steps"])

    def _evaluate(self) -> bool:
        """Every point's RVE at the strain of the current fields (from its committed state,
        on its worker); False if one of this rank's points did not relax (`_residual`
        reduces over the ranks). Collective."""
        self._strain_q.interpolate(self._strain_expr)
        self._E = self._strain_q.x.array[: self.n * self.k].reshape(self.n, self.k).copy()
        tasks = {int(g): self._E[i] - self._E_c[i] for i, g in enumerate(self.global_point)}
        answers = self._exchange(tasks, self._relax)
        ok = True
        for i, g in enumerate(self.global_point):
            got = answers.get(int(g))
            if got is None:
                ok = False
                continue
            self._S[i] = self._S_c[i] if got[0] is None else got[0]
            if got[0] is not None and self.settings.tangent == "secant":
                self._secant(i)
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
        """Fill C at the committed state of every point (module docstring). Collective;
        raises ConvergenceError on every rank if an RVE's probes did not relax."""
        s, t0 = self.settings, time.perf_counter()
        self._S_prev, self._E_prev = self._S_c.copy(), self._E_c.copy()
        if s.tangent == "initial" and self.steps_done > 0:
            return
        if self.steps_done % s.tangent_every and s.tangent != "initial":
            return

        def probe(g, rve, _):
            if s.tangent == "affine":
                return rve.affine_stiffness()
            try:
                c = rve.tangent(delta=s.tangent_delta)
            except ConvergenceError:
                return None
            self._cost[g] = self._cost.get(g, 0.0) + rve.probe_steps * rve.sim.p.n
            return c

        answers = self._exchange({int(g): None for g in self.global_point}, probe)
        failed = any(answers.get(int(g)) is None for g in self.global_point)
        if self.comm.allreduce(int(failed), MPI.MAX):
            raise ConvergenceError("an RVE's tangent probes did not relax", {})
        self._C = np.array([answers[int(g)] for g in self.global_point]).reshape(self._C.shape)
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
        if it == 0:
            # At least one Newton step: at iteration 0 the rows of moved Dirichlet values
            # hold displacements (x - g), not forces, and where no free dof carries their
            # lifting (one element, every node prescribed) they pass any force tolerance.
            return PETSc.SNES.ConvergedReason.ITERATING
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
        self._cost = {}  # the work of this attempt only (a failed one's is not the next's)
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
        for g in self._moved:
            self.held[g].commit()
        self._moved.clear()
        self._S_c, self._E_c = self._S.copy(), self._E.copy()
        self.steps_done += 1
        moved = self._rebalance()
        row = dict(step=self.steps_done, iterations=its, residuals=self.history[-1],
                   seconds=time.perf_counter() - t0, rves_moved=moved)
        self.stats["step_seconds"] += row["seconds"]
        self.log_rows.append(row)
        if self._log:
            self._log(f"FE2 step {self.steps_done}: {its} iterations, |R|/|f| "
                      + " ".join(f"{r / self._f_ref:.1e}" for r in self.history[-1])
                      + f", {row['seconds']:.1f} s")
        return its

    def _restore(self) -> None:
        self.stats["failures"] += 1
        for g in self._moved:
            self.held[g].restore()
        self._moved.clear()
        self._S, self._E = self._S_c.copy(), self._E_c.copy()
        self._C = self._C_start.copy()
        self._fill_points()

    def _rebalance(self) -> int:
        """Even the ranks' RVE work of the step just committed (`coupling.fe2_placement`).
        Returns how many RVEs moved. Collective."""
        cost = np.zeros(len(self.placement.worker))
        for part in self.comm.allgather(self._cost):
            for g, c in part.items():
                cost[g] += c
        self._cost = {}
        if self.comm.size == 1 or not np.isfinite(self.settings.imbalance):
            return 0
        return self.place(balance(cost, self.placement.worker, self.comm.size,
                                  self.settings.imbalance))

    def place(self, worker: np.ndarray) -> int:
        """Hold point g's RVE on rank ``worker[g]`` from now on (an array over the global
        points, the same on every rank): the RVEs that move travel as their committed
        state. Between load steps only. Returns how many moved. Collective."""
        worker = np.asarray(worker, np.int64)
        if worker.shape != self.placement.worker.shape or not (
                (0 <= worker) & (worker < self.comm.size)).all():
            raise ValueError(f"FE2.place: give a rank in [0, {self.comm.size}) for each of the "
                             f"{len(self.placement.worker)} points")
        leaving = np.flatnonzero(worker != self.placement.worker)
        if len(leaving) == 0:
            return 0
        mine = [int(g) for g in leaving if int(g) in self.held]
        states = {g: (self._fresh(g).state_dict(), self.held[g].solver) for g in mine}
        for g in mine:
            del self.held[g]
        for g, (state, solver) in self.placement.move(worker, states).items():
            self.held[g] = rve_from_state(state, self._prototype(g).sim.materials, solver)
        self.stats["moves"] += len(mine)
        return len(leaving)

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
        """``measure(rve)`` of every owned point (e.g. ``RVE.coordination``), at the
        committed state, measured where the RVE is held. Collective."""
        got = self._exchange({int(g): None for g in self.global_point},
                             lambda g, rve, _: measure(rve))
        return np.array([got[int(g)] for g in self.global_point])

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
                    "points/steps_done": np.int64(self.steps_done),
                    "rves/held": np.array(sorted(self.held), np.int64)})
        for g in sorted(self.held):
            out.update({f"rve/{g}/{k}": v for k, v in self._fresh(g).state_dict().items()})
        return out

    def load_state(self, d) -> None:
        """Restore :meth:`state_dict` output of the same mesh and partition."""
        if not np.array_equal(np.asarray(d["points/global"]), self.global_point):
            raise ValueError("FE2.load_state: the saved points are not this rank's (another "
                             "mesh or rank count?)")
        self.problem.load_state({k[len("problem/"):]: v for k, v in d.items()
                                 if k.startswith("problem/")})
        held = [int(g) for g in np.asarray(d.get("rves/held", self.global_point))]
        worker = np.full(len(self.placement.worker), -1, np.int64)
        for r, part in enumerate(self.comm.allgather(held)):
            worker[part] = r
        if (worker < 0).any():
            raise ValueError("FE2.load_state: the saved RVEs do not cover every point")
        self.placement.worker = worker
        old, self.held = self.held, {}
        for g in held:
            head = f"rve/{g}/"
            state = {k[len(head):]: v for k, v in d.items() if k.startswith(head)}
            rve = old.get(g)
            if rve is None:
                rve = rve_from_state(state, self._prototype(g).sim.materials,
                                     self._prototype(g).solver)
            else:
                rve.load_state(state)
                rve.commit()
            self.held[g] = rve
        self._moved.clear()
        self._S_c = np.array(d["points/stress"]).reshape(self.n, self.k)
        self._E_c = np.array(d["points/strain"]).reshape(self.n, self.k)
        self._C = np.array(d["points/tangent"]).reshape(self.n, self.k, self.k)
        self._S, self._E = self._S_c.copy(), self._E_c.copy()
        self.steps_done = int(d["points/steps_done"])
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
