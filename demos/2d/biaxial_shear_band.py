"""Shear band in plane-strain biaxial compression of a softening micropolar Drucker-Prager specimen.

This demo shows how to:

- seed a shear band with a weak spot: an initial equivalent plastic strain at one corner,
  which with softening lowers the strength there (the quadrature-point state is a field
  like any other, so an imperfection is an interpolation into it),
- follow the softening branch under displacement control with automatic cut-back
  (:func:`granfe.stepping.follow_load_path`) and a secant predictor,
- measure the band from the equivalent plastic strain gained after the peak: its
  inclination (against the Roscoe, Arthur and Coulomb angles) and its width (full width at
  half maximum of the profile across the band),
- show that with the Cosserat couple terms the band width and the softening branch
  converge under mesh refinement (the width is set by the plastic length
  ``l = sqrt(gamma / 2G)``: halving l on the finest mesh narrows it), while without them
  (coupling modulus kappa -> 0, the classical limit) the band shrinks with the elements
  and the softening branch steepens.

The specimen (width W, height 1.5 W) stands on a smooth base (held against sliding at its
bottom-right corner, away from the band) and is compressed by a smooth rigid platen (u_y
prescribed, u_x free, no rotation) after an isotropic confinement p0; its sides carry p0.
The weak spot at the bottom-left corner fixes where the band starts and so which of the
two mirror-image bands forms (the same one on any number of ranks). Cohesion softens
linearly with the equivalent plastic strain to zero (friction and dilatancy stay), so the
peak is followed by a drop to the frictional residual strength.

Run: ``mpiexec -n 2 python demos/2d/biaxial_shear_band.py [--meshes 16 24 32 --length 3e-3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem, mesh

from granfe.io import ContinuumWriter
from granfe.materials import MicropolarMaterial
from granfe.models import model_class
from granfe.models.drucker_prager import DruckerPragerMaterial
from granfe.probe import probe
from granfe.problem import ContinuumProblem
from granfe.stepping import LoadStepFailed, StepControl, follow_load_path

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--width", type=float, default=0.1, help="specimen width W [m] (height 1.5 W)")
parser.add_argument("--E", type=float, default=50e6, help="Young's modulus [Pa]")
parser.add_argument("--nu", type=float, default=0.3, help="Poisson's ratio")
parser.add_argument("--cohesion", type=float, default=50e3, help="peak cohesion c [Pa]")
parser.add_argument("--friction", type=float, default=30.0, help="friction angle phi [deg]")
parser.add_argument("--dilatancy", type=float, default=5.0, help="dilatancy angle psi [deg]")
parser.add_argument("--softening", type=float, default=0.015,
                    help="cohesion softening modulus over the shear modulus, -H / G")
parser.add_argument("--confinement", type=float, default=100e3, help="cell pressure p0 [Pa]")
parser.add_argument("--length", type=float, default=3e-3,
                    help="plastic (Cosserat) length l = sqrt(gamma / 2G) [m]")
parser.add_argument("--kappa-over-G", type=float, default=1.0,
                    help="Cosserat coupling modulus kappa over G (G = mu + kappa / 2)")
parser.add_argument("--classical-kappa-over-G", type=float, default=1e-3,
                    help="kappa / G of the contrast runs without couple terms, the classical "
                         "limit (not 0: then an iterate returned to the apex leaves the "
                         "rotation without stiffness and the factorisation fails)")
parser.add_argument("--meshes", type=int, nargs="+", default=None,
                    help="elements across the width (default 16 24 32; short: 12 16)")
parser.add_argument("--strain", type=float, default=0.025, help="final axial strain")
parser.add_argument("--out", type=Path, default=Path("output/biaxial_shear_band"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

W = args.width
H = 1.5 * W
meshes = sorted(args.meshes or ([12, 16] if SHORT else [16, 24, 32]))
G = args.E / (2 * (1 + args.nu))
lam = args.E * args.nu / ((1 + args.nu) * (1 - 2 * args.nu))
r_weak = 0.1 * W            # radius of the weak spot about the bottom-left corner
weakening = 0.2             # the weak spot starts with 20 % of the cohesion softened away
angles = {"roscoe": 45 + args.dilatancy / 2, "arthur": 45 + (args.friction + args.dilatancy) / 4,
          "coulomb": 45 + args.friction / 2}                # band against the sigma_3 (x) axis


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


def material(kappa_over_G: float, length: float) -> DruckerPragerMaterial:
    """The softening cone on micropolar elasticity with G fixed, kappa and l as given."""
    kappa = kappa_over_G * G
    elastic = MicropolarMaterial(lam=lam, mu=G - kappa / 2, kappa=kappa,
                                 gamma=2 * G * length**2, j=length**2)
    return DruckerPragerMaterial(elastic, args.cohesion, args.friction, args.dilatancy,
                                 hardening=-args.softening * G, match="plane_strain")


# ---- set-up ---------------------------------------------------------------------------
def specimen(nx: int, mat: DruckerPragerMaterial, weak: bool, prefix: str):
    """The confined specimen on an nx x 1.5 nx mesh of Q2/Q1 quadrilaterals, the weak spot
    in its state: the problem, the platen's displacement holder, its position after the
    confinement and the platen's locator."""
    ny = max(1, round(1.5 * nx))
    domain = mesh.create_rectangle(comm, [[0.0, 0.0], [W, H]], [nx, ny], mesh.CellType.quadrilateral)
    problem = ContinuumProblem(domain, model_class("micropolar_drucker_prager")(mat),
                               degree=(2, 1), prefix=prefix,
                               # a softening step either converges in a few iterations or
                               # is better cut back than iterated on
                               petsc_options={"snes_max_it": 20})

    def at(axis, value):
        return lambda x: np.isclose(x[axis], value)

    problem.fix(at(1, 0.0), "u_y")                   # smooth base
    problem.fix_point((W, 0.0), "u_x")               # against rigid sliding, off the band
    for y in (0.0, H):
        problem.fix(at(1, y), "phi")                 # platens do not rotate
    problem.traction(at(0, 0.0), (args.confinement, 0.0))
    problem.traction(at(0, W), (-args.confinement, 0.0))
    problem.traction(at(1, H), (0.0, -args.confinement))
    if weak:
        eq = problem.state.committed["equivalent_plastic_strain"]
        A, B, k0 = mat.constants
        e0 = weakening * (k0 - mat.residual_strength) / -mat.hardening
        X = ufl.SpatialCoordinate(domain)
        eq.interpolate(fem.Expression(e0 * ufl.exp(-(X[0] ** 2 + X[1] ** 2) / r_weak**2),
                                      eq.function_space.element.interpolation_points))
        eq.x.scatter_forward()
        problem.state.restore()                      # the trial state starts from it too
    problem.solve()                                  # isotropic confinement, elastic
    top = probe(problem.w.sub(0).collapse(), np.array([[W / 2, H, 0.0]]))[0][1]
    hold = problem.fix(at(1, H), "u_y", top)         # from now on displacement control
    return problem, hold, top, at(1, H)


def quadrature_points(problem) -> np.ndarray:
    """Coordinates (n, 2) of the state's quadrature points in the cells this rank owns."""
    domain = problem.domain
    Q = fem.functionspace(domain, basix.ufl.quadrature_element(
        domain.basix_cell(), value_shape=(2,), degree=problem.state.degree))
    xq = fem.Function(Q)
    xq.interpolate(fem.Expression(ufl.SpatialCoordinate(domain), Q.element.interpolation_points))
    n = Q.dofmap.index_map.size_local
    return xq.x.array[:2 * n].reshape(-1, 2).copy()


def gather(a: np.ndarray) -> np.ndarray | None:
    parts = comm.gather(a, root=0)
    return np.concatenate(parts) if comm.rank == 0 else None


def compress(nx: int, kappa_over_G: float, weak: bool = True, tag: str = "",
             length: float = args.length, picture: bool = False) -> dict:
    """Push the platen to the final axial strain; the load curve and the band (and the
    field for the picture, and VTX output)."""
    mat = material(kappa_over_G, length)
    problem, hold, top0, top = specimen(nx, mat, weak, f"biax_{tag}{nx}_")

    def apply(t):
        hold.value = top0 - t * H

    curve, peak = [], {"stress": -np.inf}

    def record(t, its):
        stress = args.confinement - problem.reaction(top, "u_y") / W     # sigma_1, compression +
        curve.append((t, stress, its))
        if stress > peak["stress"]:
            peak.update(stress=stress, strain=t,
                        eq=problem.state.owned("equivalent_plastic_strain"))

    t0 = time.perf_counter()
    final = args.strain
    # secant predictor: Newton starts from the last two converged states extrapolated, so
    # that points unloading off the band start elastic and points in it plastic
    control = StepControl(first=final / 50, min_step=final / 20000, max_step=final / 25, predictor="secant")
    stopped = None
    try:
        follow_load_path(problem, apply, final, control, on_step=record)
    except LoadStepFailed as err:          # e.g. a snap-back: no path under displacement control
        stopped = str(err)
    wall = time.perf_counter() - t0
    run = {"elements_across": nx, "h": W / nx, "kappa_over_G": kappa_over_G, "length": length,
           "weak_spot": weak,
           "dofs": problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs,
           "wall_s": wall, "steps": len(curve), "newton_iterations": int(sum(c[2] for c in curve)),
           "peak_stress": peak["stress"], "peak_strain": peak["strain"], "stopped": stopped,
           "curve": [[t, s] for t, s, _ in curve]}
    if weak:
        x = gather(quadrature_points(problem))
        de = gather(problem.state.owned("equivalent_plastic_strain") - peak["eq"])
        if comm.rank == 0:
            run["band"] = band(x, de)
        run["band"] = comm.bcast(run.get("band"), root=0)
        if picture:
            with ContinuumWriter(problem, args.out, name=f"biaxial_{tag}{nx}") as writer:
                writer.write(curve[-1][0])
            eq = gather(problem.state.owned("equivalent_plastic_strain"))     # collective
            run["field"] = None if comm.rank else {"x": x.tolist(), "eq": eq.tolist()}
    log(f"  {tag or 'cosserat'} {nx:3d}: peak {peak['stress'] / 1e3:.1f} kPa at {peak['strain']:.4f}, "
        f"end {curve[-1][1] / 1e3:.1f} kPa at {curve[-1][0]:.4f}"
        + (f", width {run['band']['fwhm'] * 1e3:.2f} mm at {run['band']['theta_deg']:.1f} deg"
           if weak else "") + f" ({wall:.1f} s, {run['newton_iterations']} its)"
        + (" STOPPED" if stopped else ""))
    return run


def band(x: np.ndarray, de: np.ndarray) -> dict:
    """Inclination and width of the band in the plastic strain gained after the peak.

    ``x`` (n, 2) quadrature points, ``de`` (n,) their equivalent plastic strain increment.
    The axis is the principal direction of the points above 30 % of the largest increment in
    the middle 60 % of the width (away from the weak spot and the far side); the profile
    across it is the mean increment in bins of W / 100 over a 0.4 W long piece about its
    centre; the width is the profile's full width at half maximum."""
    middle = (x[:, 0] > 0.2 * W) & (x[:, 0] < 0.8 * W)
    if not de[middle].max() > 0:
        raise RuntimeError("no plastic strain gained after the peak: push further (--strain)")
    hot = middle & (de > 0.3 * de[middle].max())
    weights, pts = de[hot], x[hot]
    centre = weights @ pts / weights.sum()
    cov = ((pts - centre).T * weights) @ (pts - centre) / weights.sum()
    t = np.linalg.eigh(cov)[1][:, 1]
    t = t * np.sign(t[0])
    normal = np.array([-t[1], t[0]])
    across, along = (x - centre) @ normal, (x - centre) @ t
    piece = (np.abs(along) < 0.2 * W) & (np.abs(across) < 0.4 * W)
    edges = np.arange(-0.4 * W, 0.4 * W + 1e-12 * W, W / 100)
    which = np.digitize(across[piece], edges) - 1
    sums = np.bincount(which, weights=de[piece], minlength=len(edges) - 1)
    counts = np.bincount(which, minlength=len(edges) - 1)
    ok = counts > 0
    d, profile = (0.5 * (edges[1:] + edges[:-1]))[ok], sums[ok] / counts[ok]
    k = int(np.argmax(profile))
    half = profile[k] / 2
    i = k
    while i > 0 and profile[i] > half:
        i -= 1
    j = k
    while j < len(profile) - 1 and profile[j] > half:
        j += 1
    left = np.interp(half, [profile[i], profile[i + 1]], [d[i], d[i + 1]])
    right = np.interp(half, [profile[j], profile[j - 1]], [d[j], d[j - 1]])
    return {"theta_deg": float(np.degrees(np.arctan2(t[1], t[0]))), "fwhm": float(right - left),
            "integral_width": float(np.trapezoid(profile, d) / profile[k]),
            "centre": centre.tolist(), "max_increment": float(profile[k]),
            "profile": [d.tolist(), profile.tolist()]}


# ---- solve ----------------------------------------------------------------------------
log(f"biaxial shear band: W = {W} m, l = {args.length} m, H/G = {-args.softening}, "
    f"meshes {meshes}")
homogeneous = compress(1, args.kappa_over_G, weak=False, tag="homogeneous")
cosserat = [compress(nx, args.kappa_over_G, tag="cosserat", picture=nx == meshes[-1]) for nx in meshes]
classical = [compress(nx, args.classical_kappa_over_G, tag="classical", picture=nx == meshes[-1])
             for nx in meshes]
# the width is the Cosserat length's: half of it on the finest mesh
half_length = None if SHORT else compress(meshes[-1], args.kappa_over_G, tag="half_length",
                                          length=args.length / 2)


def curve_spread(runs) -> float:
    """Largest difference of the load curves from the finest mesh's, over its peak stress,
    on the strains all runs reached."""
    if len(runs) < 2:
        return 0.0
    ref = np.array(runs[-1]["curve"])
    end = min(r["curve"][-1][0] for r in runs)
    grid = np.linspace(0, end, 200)
    finest = np.interp(grid, *ref.T)
    return float(max(np.abs(np.interp(grid, *np.array(r["curve"]).T) - finest).max()
                     for r in runs[:-1]) / runs[-1]["peak_stress"])


def width_spread(runs) -> float:
    widths = [r["band"]["fwhm"] for r in runs]
    return float(max(widths) / min(widths) - 1)


summary = {
    "cosserat_width_spread": width_spread(cosserat),
    "cosserat_width_over_length": [r["band"]["fwhm"] / args.length for r in cosserat],
    "classical_width_over_h": [r["band"]["fwhm"] / r["h"] for r in classical],
    "classical_width_ratio_coarse_to_fine": classical[0]["band"]["fwhm"] / classical[-1]["band"]["fwhm"],
    "cosserat_curve_spread": curve_spread(cosserat),
    "classical_curve_spread": curve_spread(classical),
    "peak_below_homogeneous": [1 - r["peak_stress"] / homogeneous["peak_stress"] for r in cosserat],
    "half_length_width_ratio": None if half_length is None else
    half_length["band"]["fwhm"] / cosserat[-1]["band"]["fwhm"],
    "band_angles_deg": {"cosserat": [r["band"]["theta_deg"] for r in cosserat],
                        "classical": [r["band"]["theta_deg"] for r in classical], **angles},
}
log(f"Cosserat widths {[round(r['band']['fwhm'] * 1e3, 2) for r in cosserat]} mm "
    f"(spread {100 * summary['cosserat_width_spread']:.1f} %, "
    f"{summary['cosserat_width_over_length'][-1]:.1f} l); classical "
    f"{[round(r['band']['fwhm'] * 1e3, 2) for r in classical]} mm; curve spread Cosserat "
    f"{100 * summary['cosserat_curve_spread']:.1f} %, classical {100 * summary['classical_curve_spread']:.1f} %")
log("band angles: Cosserat " + ", ".join(f"{a:.1f}" for a in summary["band_angles_deg"]["cosserat"])
    + "; classical " + ", ".join(f"{a:.1f}" for a in summary["band_angles_deg"]["classical"])
    + f"; Roscoe {angles['roscoe']:.1f}, Arthur {angles['arthur']:.1f}, Coulomb {angles['coulomb']:.1f}")
if half_length is not None:
    log(f"half the length on {meshes[-1]} elements: width x {summary['half_length_width_ratio']:.2f}")

# ---- plots and checks -----------------------------------------------------------------
fields = {name: runs[-1].pop("field") for name, runs in (("cosserat", cosserat), ("classical", classical))}
results = {
    "what": "plane-strain biaxial compression of a softening micropolar Drucker-Prager specimen "
            "(cohesion softening to zero, weak spot at the bottom-left corner): band width and "
            "load curves with the Cosserat couple terms and without them (kappa -> 0)",
    "inputs": {"width": W, "height": H, "E": args.E, "nu": args.nu, "cohesion": args.cohesion,
               "friction_deg": args.friction, "dilatancy_deg": args.dilatancy,
               "softening_over_G": args.softening, "confinement": args.confinement,
               "plastic_length": args.length, "kappa_over_G": args.kappa_over_G,
               "classical_kappa_over_G": args.classical_kappa_over_G, "meshes": meshes,
               "final_strain": cosserat[0]["curve"][-1][0], "weak_spot_radius": r_weak,
               "weak_spot_softened_fraction": weakening, "elements": "Q2 (u) / Q1 (phi), 3x3 Gauss",
               "short": SHORT, "ranks": comm.size},
    "summary": summary, "homogeneous": homogeneous, "cosserat": cosserat, "classical": classical,
    "half_length": half_length,
}
if comm.rank == 0:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    args.out.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(14, 6.5))
    grid = fig.add_gridspec(2, 4, width_ratios=[1, 1, 1.7, 1.7])
    titles = {"cosserat": "Cosserat", "classical": "no couple terms"}
    for k, (name, f) in enumerate(fields.items()):
        ax = fig.add_subplot(grid[:, k])
        x, e = np.array(f["x"]), np.array(f["eq"])
        tri = ax.tripcolor(Triangulation(x[:, 0] * 1e3, x[:, 1] * 1e3), e, shading="gouraud",
                           cmap="magma")
        fig.colorbar(tri, ax=ax, orientation="horizontal", pad=0.08, label="equivalent plastic strain")
        b = (cosserat if name == "cosserat" else classical)[-1]["band"]
        ax.set_title(f"{titles[name]}, {meshes[-1]} elements across\nband {b['fwhm'] * 1e3:.1f} mm wide, "
                     f"at {b['theta_deg']:.1f} deg", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
    ax = fig.add_subplot(grid[0, 2:])
    for runs, style in ((cosserat, "-"), (classical, "--")):
        for r in runs:
            t, s = np.array(r["curve"]).T
            ax.plot(100 * t, s / 1e3, style, label=f"{'Cosserat' if style == '-' else 'no couple terms'} "
                    f"{r['elements_across']}")
    t, s = np.array(homogeneous["curve"]).T
    ax.plot(100 * t, s / 1e3, ":", color="k", label="homogeneous (no weak spot)")
    if half_length is not None:
        t, s = np.array(half_length["curve"]).T
        ax.plot(100 * t, s / 1e3, "-.", color="0.4", label=f"Cosserat {meshes[-1]}, l / 2")
    ax.set_xlabel("axial strain [%]")
    ax.set_ylabel("sigma_1 [kPa]")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(grid[1, 2:])
    for runs, style in ((cosserat, "-"), (classical, "--")):
        for r in runs:
            d, p = np.array(r["band"]["profile"])
            ax.plot(d * 1e3, p / p.max(), style, label=f"{'Cosserat' if style == '-' else 'no couple terms'} "
                    f"{r['elements_across']}")
    if half_length is not None:
        d, p = np.array(half_length["band"]["profile"])
        ax.plot(d * 1e3, p / p.max(), ":", color="k", label=f"Cosserat {meshes[-1]}, l / 2")
    ax.set_xlabel("distance across the band [mm]")
    ax.set_ylabel("post-peak plastic strain / max")
    ax.set_xlim(-0.25e3 * W, 0.25e3 * W)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "biaxial_shear_band.png", dpi=110)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))

# the Cosserat band converges, the classical one follows the elements
assert summary["cosserat_width_spread"] < 0.1, summary["cosserat_width_spread"]
assert summary["classical_width_ratio_coarse_to_fine"] > 1.15, summary
assert all(c["band"]["fwhm"] > 2 * k["band"]["fwhm"] for c, k in zip(cosserat, classical, strict=True))
assert all(0 <= d < 0.05 for d in summary["peak_below_homogeneous"]), summary["peak_below_homogeneous"]
assert all(angles["roscoe"] - 3 < a < angles["coulomb"] for a in summary["band_angles_deg"]["cosserat"])
