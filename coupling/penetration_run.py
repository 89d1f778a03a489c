"""Run a coupled penetration with outputs: q_c / f_s against depth (CSV, JSON, PNG), grains
(VTU/PVD), continuum (VTX) and a picture of both. Used by ``granfe run`` (kind
``penetration``) and ``demos/2d/cpt_coupled.py``."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np

from coupling.penetration import CoupledPenetration, PenetrationParameters

__all__ = ["run_penetration"]


def run_penetration(prm: PenetrationParameters, out: str | Path, comm, *, frames: int = 5,
                    fields: bool = True, particles: bool = True, png: bool = True,
                    progress: bool = True, log=None) -> dict:
    """Set up, run and write a coupled penetration into ``out``; returns the results dict."""
    from coupling.penetration import CouplingUnstable
    from dem.errors import BlowUpError, DemError
    from dem.io import ParticleWriter, save_state
    from granfe.io import ContinuumWriter, render_png

    out = Path(out)
    log = log or (lambda msg: print(msg, flush=True) if comm.rank == 0 else None)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    t0 = time.perf_counter()
    cpt = CoupledPenetration(prm, comm, log=log)
    t_setup = time.perf_counter() - t0
    log(f"set-up {t_setup:.1f} s: {cpt.n_grains} grains, coordination "
        f"{cpt.contact_stats['coordination']:.2f}; continuum lam = mu = {cpt.material_fe.lam:.3g} Pa, "
        f"kappa = {cpt.material_fe.kappa:.3g} Pa, rho = {cpt.material_fe.rho:.0f} kg/m^3")
    grains = ParticleWriter(out, "grains") if (particles and comm.rank == 0) else None
    writer = ContinuumWriter(cpt.problem, out, name="continuum") if fields else None
    n_steps = int(np.ceil(prm.depth / prm.velocity / cpt.dt_fe))
    every = max(1, n_steps // frames)
    bar = None
    if progress and comm.rank == 0:
        from tqdm import tqdm
        bar = tqdm(total=n_steps, unit="FE step", desc="penetration")

    def on_step(h):
        if bar is not None:
            bar.set_postfix(depth=f"{h['depth'] * 1e3:.1f} mm", q_c=f"{h['q_c'] / 1e3:.2f} kPa",
                            step=f"{h['wall_time']:.2f} s")
            bar.update(1)
        if h["step"] % every and h["step"] != n_steps:
            return
        if writer is not None:
            writer.write(h["time"])
        if grains is not None:
            p = cpt.sim.p
            grains.write(h["time"], p.x, p.radius, velocity=p.v, kind=p.kind.astype(float), force=p.force)

    t0 = time.perf_counter()
    try:
        history = cpt.run(progress=on_step)
    except (BlowUpError, DemError, CouplingUnstable, FloatingPointError, ValueError) as err:
        where = out / "last_good"
        cpt.problem.write_checkpoint(where)
        if comm.rank == 0:
            save_state(where / "grains.npz", **cpt.sim.p.state_dict())
            (out / "history.json").write_text(json.dumps({"steps": cpt.history}, indent=2, default=float))
        raise RuntimeError(f"penetration stopped at depth {cpt.history[-1]['depth'] if cpt.history else 0:.4g} m: "
                           f"{err}; the last state and the history so far are in {where}") from err
    finally:
        if bar is not None:
            bar.close()
    t_run = time.perf_counter() - t0
    if writer is not None:
        writer.close()
    if grains is not None:
        grains.close()
    if png:
        p = cpt.sim.p

        def overlay(plotter, warp):
            import pyvista
            cloud = pyvista.PolyData(p.x.copy())
            cloud["kind"] = p.kind.astype(float)
            plotter.add_mesh(cloud, scalars="kind", cmap=["white", "red"], point_size=3,
                             render_points_as_spheres=True, show_scalar_bar=False)

        W = 0.5 * prm.chamber_width
        render_png(cpt.problem, out / "cpt.png", "u_magnitude", warp=0, overlay=overlay,
                   box=(-W / 2, W / 2, cpt.surface - min(0.12, prm.chamber_depth), cpt.surface + 0.03),
                   title=f"|u| of the continuum; grains (red: ghosts, cone), depth {prm.depth * 100:.1f} cm")
    results = {"parameters": prm.__dict__, "grains": cpt.n_grains,
               "continuum": {"lam": cpt.material_fe.lam, "mu": cpt.material_fe.mu,
                             "kappa": cpt.material_fe.kappa, "rho": cpt.material_fe.rho,
                             "dofs": cpt.problem.V.dofmap.index_map.size_global},
               "packing": cpt.contact_stats, "dem_dt": cpt.sim.dt, "fe_dt": cpt.dt_fe,
               "dem_steps": cpt.sim.nsteps, "setup_time_s": t_setup, "run_time_s": t_run,
               "ranks": comm.size, "history": history,
               "q_c_mean_last_half": float(np.mean([h["q_c"] for h in history[len(history) // 2:]]))}
    if comm.rank == 0:
        (out / "results.json").write_text(json.dumps(results, indent=2, default=float))
        with open(out / "tip_resistance.csv", "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=list(history[0]))
            wr.writeheader()
            wr.writerows(history)
        if png:
            import matplotlib.pyplot as plt

            depth = np.array([h["depth"] for h in history]) * 100
            fig, axes = plt.subplots(1, 2, figsize=(8, 5), sharey=True)
            axes[0].plot([h["q_c"] / 1e3 for h in history], depth)
            axes[0].set_xlabel("tip resistance q_c [kPa]")
            axes[0].set_ylabel("depth [cm]")
            axes[0].invert_yaxis()
            axes[1].plot([h["f_s"] / 1e3 for h in history], depth)
            axes[1].set_xlabel("sleeve friction f_s [kPa]")
            fig.tight_layout()
            fig.savefig(out / "tip_resistance.png", dpi=120)
        log(f"{len(history)} FE steps, {cpt.sim.nsteps} DEM steps in {t_run:.1f} s; outputs in {out}")
    return results
