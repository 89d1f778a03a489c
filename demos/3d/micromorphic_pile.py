"""A micromorphic continuum coupled to the grains: the 3D pile penetration
(`scenes/pile_3d_micromorphic.toml`), with the grains' seed 002 stress measures set beside the
continuum's sigma, s and m.

This demo shows how to:

- run a penetration scene whose continuum is micromorphic (``[continuum] model =
  "micromorphic"``: u and phi = chi - I, 12 dofs a node; phi at the window's prescribed nodes
  fitted to the grains' displacements, the ghosts turning with the axial vector of
  skew(phi), `coupling.micro_kinematics`) with the outputs and checkpoints of ``granfe run``
  (`coupling.apps.penetration.run.run_penetration`),
- continue it from its last checkpoint as ``granfe restart`` does and check that the
  continuation repeats the run's last FE steps to the bit,
- measure, along the continuation, the grains' micromorphic stresses over averaging boxes
  split into RVEs (`dem.stress.micromorphic_stress`, seed 002 eq. 1-15: micro-stress s, couple
  stress m, Cauchy sigma from the balance of first moment of momentum, with gravity) and the
  continuum's sigma, s and m averaged over the cells whose midpoints lie in the same boxes.

Conventions: both tension positive. The grains' unsymmetric tensors carry the branch (face)
index first (``t_l = n_k sigma_kl``), the continuum's the face index last (``t_i = sigma_ij
n_j``): the grains' sigma is transposed before it is compared. m: the grains' first moment
``m_klm = <sigma'_kl xi_m>``, the continuum's double stress ``m_ijk`` (conjugate to
``phi_ij,k``); both are summarised by seed 002's couple measures (|p^c|, tau^c, eq. 14-15).

Run: ``mpiexec -n 2 python demos/3d/micromorphic_pile.py`` (or serially); writes
``benchmarks/results/micromorphic_pile.json`` and ``.png`` (``--results``), the run's
outputs in ``--out`` (default ``output/micromorphic_pile/``). ``GRANFE_SHORT=1``: a 6 mm push.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

SHORT = os.environ.get("GRANFE_SHORT") == "1"
ROOT = Path(__file__).resolve().parents[2]

parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--scene", type=Path, default=ROOT / "scenes" / "pile_3d_micromorphic.toml")
parser.add_argument("--set", nargs="*", default=[], help="scene overrides, section.key=value")
parser.add_argument("--out", type=Path, default=Path("output/micromorphic_pile"))
parser.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results" / "micromorphic_pile.json")
parser.add_argument("--every", type=int, default=5, help="FE steps between stress measurements")
parser.add_argument("--no-micropolar", dest="micropolar", action="store_false",
                    help="skip the micropolar continuum's run in the same boxes")
args = parser.parse_args()


def boxes(prm, top):
    """The averaging boxes (lo, hi, RVE divisions) [m]: under the pile's final tip, beside
    its shaft, and in the overlap band under the prescribed nodes (the handshake layer above
    the window's base)."""
    R, d, a, b = prm.cone_radius, 2 * prm.radius, prm.window_half_width, prm.window_depth
    tip = top - prm.depth
    hs = prm.handshake * prm.element_size_window
    return {
        "under the tip": ((-1.5 * R, -1.5 * R, tip - 2.5 * R), (1.5 * R, 1.5 * R, tip - 0.5 * R), (2, 2, 2)),
        "beside the shaft": ((R + 0.5 * d, -R, tip), (a - 0.5 * d, R, top - 2 * d), (2, 2, 2)),
        "overlap band": ((-(a - d), -(a - d), -b + 0.5 * d), (a - d, a - d, -b + hs), (2, 2, 1)),
    }


class ContinuumBoxes:
    """Volume averages of the continuum's stresses over the owned cells whose midpoints lie in
    each box (stresses interpolated into DG0: the cell means of a P1 u and phi)."""

    def __init__(self, problem, box_list):
        import ufl
        from dolfinx import fem
        from dolfinx.mesh import compute_midpoints

        dom = problem.domain
        self.comm = dom.comm
        tdim = dom.topology.dim
        n = dom.topology.index_map(tdim).size_local
        mid = compute_midpoints(dom, tdim, np.arange(n, dtype=np.int32))
        V0 = fem.functionspace(dom, ("Discontinuous Lagrange", 0))
        vol = fem.assemble_vector(fem.form(ufl.TestFunction(V0) * ufl.dx)).array[:n]
        self.weights = {}
        for name, (lo, hi, _) in box_list.items():
            inside = np.all((mid >= np.asarray(lo)) & (mid <= np.asarray(hi)), axis=1)
            self.weights[name] = np.where(inside, vol, 0.0)
        self.n, self.exprs = n, {}
        u = ufl.split(problem.w)[0]
        for key, expr in (problem.stresses() | {"grad_u": ufl.grad(u)}).items():
            S = fem.functionspace(dom, ("Discontinuous Lagrange", 0, ufl.shape(expr)))
            self.exprs[key] = (fem.Expression(expr, S.element.interpolation_points), fem.Function(S))

    def averages(self) -> dict:
        out = {name: {} for name in self.weights}
        for key, (expr, f) in self.exprs.items():
            f.interpolate(expr)
            shape = f.function_space.value_shape
            values = f.x.array.reshape(-1, int(np.prod(shape)))[: self.n]
            for name, w in self.weights.items():
                s = self.comm.allreduce(w @ values)
                out[name][key] = (s / self.comm.allreduce(w.sum())).reshape(shape)
        return out


def strains(H) -> dict:
    """Volumetric strain tr(H) and the magnitude |dev sym H| of a displacement gradient H."""
    e = 0.5 * (np.asarray(H) + np.asarray(H).T)
    return {"vol_strain": float(np.trace(e)), "dev_strain": float(np.linalg.norm(e - np.trace(e) / 3 * np.eye(3)))}


def grain_measures(cpt, box_list) -> dict:
    """Seed 002's measures of the grains in each box (gravity in the body couple; the
    accelerations are not kept by the run, so no micro-spin inertia), and the displacement
    gradient of the free grains settled in the box (least-squares affine fit, from the
    settled packing)."""
    from dem.stress import AveragingDomain, micromorphic_stress

    p = cpt.grain_state()
    n, X = cpt.n_grains, cpt.x_ref
    free = cpt.kinds == 0
    pairs, force = cpt.sim.contact_forces()
    g = np.array([0.0, 0.0, -cpt.prm.gravity])
    out = {}
    for name, (lo, hi, div) in box_list.items():
        m = micromorphic_stress(AveragingDomain(lo, hi, div), p.x, p.radius, pairs, force, p.mass,
                                gravity=g, on_empty="zero")
        inside = free & np.all((X >= np.asarray(lo)) & (X <= np.asarray(hi)), axis=1)
        fit = np.linalg.lstsq(np.c_[np.ones(inside.sum()), X[inside]], p.x[:n][inside] - X[inside], rcond=None)[0]
        out[name] = {"s": m.s, "sigma": m.sigma.T, "m": m.m, "sigma_G": m.sigma_G.T, "grad_u": fit[1:].T,
                     "contacts": int(m.rve_contacts.sum()), "empty_rves": int((m.rve_contacts == 0).sum())}
    return out


def summary(t: dict) -> dict:
    """Mean stress, octahedral shear (of the symmetric part) and couple measures [Pa, Pa m]."""
    from dem.stress import couple_measures, mean_stress, octahedral_shear

    out = {}
    for key in ("sigma", "s"):
        a = np.asarray(t[key])
        out[f"p_{key}"] = mean_stress(a)
        out[f"tau_{key}"] = octahedral_shear(0.5 * (a + a.T))
        out[f"skew_{key}"] = float(np.linalg.norm(0.5 * (a - a.T)))
    out["p_couple"], out["tau_couple"] = couple_measures(t["m"])
    return out


def continuum_summary(cont: dict) -> dict:
    """:func:`summary` of a continuum's box averages: the micromorphic sigma, s and m; a
    micropolar continuum has only sigma (its couple stress is not a double stress)."""
    if "micro_stress" in cont:
        return summary({"sigma": cont["sigma"], "s": cont["micro_stress"], "m": cont["higher_order_stress"]})
    out = {k: v for k, v in summary({"sigma": cont["sigma"], "s": cont["sigma"], "m": np.zeros((3, 3, 3))}).items()
           if "sigma" in k}
    return out


def measured_push(prm, comm, log, every, checkpoint_at=None, where=None):
    """A fresh coupled run of ``prm`` pushed to the end with the grains' and the continuum's
    box measures every ``every`` FE steps (and at the start); a checkpoint at step
    ``checkpoint_at`` into ``where``. Returns (run, series, last grains, last continuum)."""
    from coupling.apps.penetration.coupled import CoupledPenetration

    cpt = CoupledPenetration(prm, comm, log=log)
    box_list = boxes(prm, float(cpt.x_ref[:, 2].max()))
    fe_boxes = ContinuumBoxes(cpt.problem, box_list)
    series, start = [], {}

    def measure():
        grains, cont = grain_measures(cpt, box_list), fe_boxes.averages()
        for name in box_list:   # the continuum's strain from the start (a 3D run starts geostatic)
            start.setdefault(name, cont[name]["grad_u"])
        series.append({"step": len(cpt.history), "depth": cpt.depth, "boxes": {
            name: {"grains": summary(grains[name]) | strains(grains[name]["grad_u"]),
                   "continuum": continuum_summary(cont[name]) | strains(cont[name]["grad_u"] - start[name]),
                   "grain_contacts": grains[name]["contacts"], "empty_rves": grains[name]["empty_rves"]}
            for name in box_list}})
        return grains, cont

    grains, cont = measure()
    while len(cpt.history) < cpt.n_steps:
        stop = cpt.n_steps if checkpoint_at is None or len(cpt.history) >= checkpoint_at else checkpoint_at
        cpt.run(steps=min(every - len(cpt.history) % every, stop - len(cpt.history)))
        if len(cpt.history) == checkpoint_at:
            cpt.save_checkpoint(where)
        if len(cpt.history) % every == 0 or len(cpt.history) == cpt.n_steps:
            grains, cont = measure()
    return cpt, box_list, series, grains, cont


def main():
    from dataclasses import replace

    from coupling.apps.penetration.coupled import CoupledPenetration
    from coupling.apps.penetration.run import run_penetration
    from coupling.scene import load_scene, parse_overrides

    comm = MPI.COMM_WORLD
    sets = list(args.set) + (["penetrator.depth=0.006"] if SHORT else [])
    scene = load_scene(args.scene, parse_overrides(sets))
    prm, o = scene.parameters(), scene.output

    def log(msg):
        if comm.rank == 0:
            print(msg, flush=True)

    def clocks():
        return time.perf_counter(), comm.allreduce(time.process_time())

    # ---- 1. the run, as `granfe run`: outputs and checkpoints -------------------------------
    t0, c0 = clocks()
    first = run_penetration(prm, args.out / "run", comm, frames=o.frames, fields=o.fields,
                            particles=o.particles, png=o.png, progress=False, log=log,
                            checkpoint_every=o.checkpoint_every)
    t1, c1 = clocks()
    files = sorted(p.name for p in (args.out / "run").iterdir()) if comm.rank == 0 else None

    # ---- 2. the same run again, measured, with a checkpoint half-way ------------------------
    where = args.out / "mid_checkpoint"
    n_half = len(first["history"]) // 2
    cpt, box_list, series, grains, cont = measured_push(prm, comm, log, args.every, n_half, where)
    t2, c2 = clocks()
    repeat = [h["q_c"] for h in cpt.history] == [h["q_c"] for h in first["history"]]

    # ---- 3. the continuation from that checkpoint, as `granfe restart` ----------------------
    again = CoupledPenetration(prm, comm, log=log, checkpoint=where)
    start = len(again.history)
    again.run()
    t3, c3 = clocks()
    same = [a["q_c"] == b["q_c"] and a["depth"] == b["depth"]
            for a, b in zip(cpt.history[start:], again.history[start:], strict=True)]
    same_state = bool(np.array_equal(again.problem.w.x.array, cpt.problem.w.x.array)
                      and np.array_equal(again.sim.p.x, cpt.sim.p.x))

    # ---- 4. the micropolar continuum in the same boxes --------------------------------------
    micropolar = None
    if args.micropolar:
        mp, _, mp_series, _, mp_cont = measured_push(replace(prm, continuum="micropolar"), comm, log, args.every)
        micropolar = {"series": mp_series, "q_c": [h["q_c"] for h in mp.history],
                      "final_sigma": {name: np.asarray(mp_cont[name]["sigma"]).tolist() for name in box_list}}
    t4, c4 = clocks()

    fit = cpt.interface.micro
    mat = cpt.problem.model.material
    results = {
        "scene": str(args.scene.relative_to(ROOT)) if args.scene.is_relative_to(ROOT) else str(args.scene),
        "overrides": sets, "ranks": comm.size,
        "parameters": dict(prm.__dict__),
        "continuum_material": mat.moduli() | {"rho": mat.rho, "micro_inertia": mat.micro_inertia},
        "micropolar_estimate": {k: getattr(cpt.material_fe, k) for k in ("lam", "mu", "kappa", "gamma", "rho", "j")},
        "grains": cpt.n_grains,
        "dofs": cpt.problem.V.dofmap.index_map.size_global * cpt.problem.V.dofmap.index_map_bs,
        "prescribed_nodes": comm.allreduce(fit.prescribed.size) // 9,
        "fit": {"min_grains": fit.min_grains, "min_spread": fit.min_spread,
                "grains_per_node_min": comm.allreduce(float(fit.grains_per_node.min(initial=np.inf)), MPI.MIN),
                "grains_per_node_max": comm.allreduce(float(fit.grains_per_node.max(initial=0.0)), MPI.MAX),
                "spread_min": comm.allreduce(float(fit.spread.min(initial=np.inf)), MPI.MIN)},
        "run": {"fe_steps": len(first["history"]), "q_c_mean_last_half": first["q_c_mean_last_half"],
                "setup_time_s": first["setup_time_s"], "push_time_s": first["run_time_s"],
                "wall_s": t1 - t0, "cpu_s_all_ranks": c1 - c0, "outputs": files,
                "history": [{k: h[k] for k in ("step", "depth", "q_c", "f_s", "interface_mismatch")}
                            for h in first["history"]]},
        "repeat": {"same_q_c_every_step": repeat, "wall_s": t2 - t1, "cpu_s_all_ranks": c2 - c1},
        "restart": {"from_step": start, "steps_continued": len(same), "bit_identical_steps": int(sum(same)),
                    "same_final_state": same_state, "wall_s": t3 - t2, "cpu_s_all_ranks": c3 - c2},
        "boxes": {name: {"lo": lo, "hi": hi, "divisions": div} for name, (lo, hi, div) in box_list.items()},
        "stress_series": series,
        "final_tensors": {name: {"grains": {k: np.asarray(grains[name][k]).tolist() for k in ("s", "sigma", "m")},
                                 "continuum": {k: np.asarray(cont[name][k]).tolist() for k in cont[name]}}
                          for name in box_list},
        "micropolar": micropolar,
        "micropolar_wall_s": t4 - t3, "micropolar_cpu_s_all_ranks": c4 - c3,
    }
    if comm.rank == 0:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1, default=float))
        plot(results, args.results.with_suffix(".png"))
        last = series[-1]["boxes"]
        for name in box_list:
            g, c = last[name]["grains"], last[name]["continuum"]
            log(f"{name}: p_s grains {g['p_s']:.4g} Pa, continuum {c['p_s']:.4g} Pa; p_sigma {g['p_sigma']:.4g} / "
                f"{c['p_sigma']:.4g} Pa; tau_s {g['tau_s']:.4g} / {c['tau_s']:.4g} Pa; tau^c {g['tau_couple']:.3g} / "
                f"{c['tau_couple']:.3g} Pa m; volumetric strain {g['vol_strain']:.3g} / {c['vol_strain']:.3g}")
        log(f"repeat identical: {repeat}; restart from step {start}: {int(sum(same))} of {len(same)} steps "
            f"bit-identical, final state identical: {same_state}; CPU s (all ranks): run {c1 - c0:.0f}, measured "
            f"{c2 - c1:.0f}, restart {c3 - c2:.0f}, micropolar {c4 - c3:.0f}; results in {args.results}")


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(2, 3, figsize=(17, 9))
    h = results["run"]["history"]
    ax = axes[0, 0]
    ax.plot([r["depth"] * 1e3 for r in h], [r["q_c"] / 1e3 for r in h], label="micromorphic: run")
    s = results["restart"]["from_step"]
    ax.plot([r["depth"] * 1e3 for r in h[s:]], [r["q_c"] / 1e3 for r in h[s:]], "k.", ms=3,
            label=f"restart from step {s} ({results['restart']['bit_identical_steps']}/"
                  f"{results['restart']['steps_continued']} steps bit-identical)")
    if results["micropolar"] is not None:
        ax.plot([r["depth"] * 1e3 for r in h], [q / 1e3 for q in results["micropolar"]["q_c"]], color="0.6",
                lw=0.8, label="micropolar continuum")
    ax.set_xlabel("pile depth [mm]")
    ax.set_ylabel("q_c [kPa]")
    ax.set_title("pile into grains coupled to a micromorphic continuum", fontsize=10)
    ax.legend(fontsize=8)
    series = results["stress_series"]
    depth = np.array([r["depth"] for r in series]) * 1e3
    colours = dict(zip(results["boxes"], ("C0", "C1", "C2"), strict=False))
    styles = {"grains' s (seed 002)": dict(ls="-", marker="o", ms=3),
              "grains' sigma (eq. 10-12)": dict(ls=":"),
              "continuum's s": dict(ls="--", marker="s", ms=3),
              "continuum's sigma": dict(ls="-.", lw=0.8),
              "micropolar continuum's sigma": dict(ls="none", marker="x", ms=4)}
    for ax, key, sign, label in ((axes[0, 1], "p_s", -1.0, "mean stress -p [kPa] (compression > 0)"),
                                 (axes[1, 0], "tau_s", 1.0, "octahedral shear of sym [kPa]")):
        sig = key.replace("_s", "_sigma")
        for name, c in colours.items():
            b = [r["boxes"][name] for r in series]
            for what, source, k in (("grains' s (seed 002)", "grains", key),
                                    ("grains' sigma (eq. 10-12)", "grains", sig),
                                    ("continuum's s", "continuum", key), ("continuum's sigma", "continuum", sig)):
                ax.plot(depth, [sign * r[source][k] / 1e3 for r in b], color=c, **styles[what])
            if results["micropolar"] is not None:
                mp = results["micropolar"]["series"]
                ax.plot([r["depth"] * 1e3 for r in mp], [sign * r["boxes"][name]["continuum"][sig] / 1e3 for r in mp],
                        color=c, **styles["micropolar continuum's sigma"])
        ax.set_xlabel("pile depth [mm]")
        ax.set_ylabel(label)
    ax = axes[1, 1]
    for name, c in colours.items():
        ax.semilogy(depth, [r["boxes"][name]["grains"]["tau_couple"] for r in series], color=c,
                    **styles["grains' s (seed 002)"])
        ax.semilogy(depth, [max(r["boxes"][name]["continuum"]["tau_couple"], 1e-12) for r in series], color=c,
                    **styles["continuum's s"])
    ax.set_xlabel("pile depth [mm]")
    ax.set_ylabel("tau^c of m [Pa m]: grains (o), continuum (s)")
    for ax, key, label in ((axes[0, 2], "vol_strain", "volumetric strain (> 0: dilation)"),
                           (axes[1, 2], "dev_strain", "|dev eps|")):
        for name, c in colours.items():
            ax.plot(depth, [r["boxes"][name]["grains"][key] for r in series], color=c, **styles["grains' s (seed 002)"])
            ax.plot(depth, [r["boxes"][name]["continuum"][key] for r in series], color=c, **styles["continuum's s"])
        ax.set_xlabel("pile depth [mm]")
        ax.set_ylabel(label + ": grains' fit (o), continuum (s)")
    handles = [Line2D([], [], color=c, lw=3, label=name) for name, c in colours.items()]
    handles += [Line2D([], [], color="k", label=what, **st) for what, st in styles.items()]
    axes[0, 1].legend(handles=handles, fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
