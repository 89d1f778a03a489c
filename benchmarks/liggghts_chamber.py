"""The 3D virtual calibration chamber in LIGGGHTS-PUBLIC 3.8: the peer run of our full-DEM
chamber (:class:`coupling.apps.penetration.coupled.DemPenetration` with ``dim = 3`` and a
``vertical_stress``), so that the benchmark can time the tool a user would pick instead, on
the same chamber, packing and contact law.

What the peer does (:func:`write_case` writes it, :func:`run_case` runs it):

- the grains: EXACTLY our packing, :func:`~coupling.apps.penetration.coupled.grain_lattice`
  with ``np.random.default_rng(prm.seed)`` as ``DemPenetration`` draws it (same centres and
  radii), written as a LIGGGHTS data file (atom_style granular, units si);
- the contact law: Hertz-Mindlin (``pair_style gran model hertz tangential history
  limitForce on``), E, nu, friction and restitution of the parameters, LIGGGHTS' beta(e)
  damping, which is our law's (:mod:`dem.contact.hertz_mindlin`); the box's side and bottom
  walls and the top plate are a second atom type of the same E and nu, frictionless with
  the grains (our ``smooth_walls``); the cone is of the grains' type (their friction);
- the box: ``fix wall/gran ... primitive`` planes at x, y = +-W/2 and z = -H; gravity 9.81
  down z; time step 0.2 of the smallest grain's Rayleigh step x ``dt_factor`` (ours);
- the top plate: a square STL (two triangles, a grain diameter wider than the box on every
  side, so that no grain meets its edge) at the highest grain's top, servo-controlled with
  ``fix mesh/surface/stress/servo`` (force control along z, pure P controller) at
  ``vertical_stress x W^2``; its gain is our ``plate_servo``'s (speed ``0.2 (sigma_v -
  sigma) / (rho c)``, ``kp = gain sigma_v / vel_max``), ``vel_max`` ours (``max(velocity,
  0.1)``);
- consolidation: dynamic relaxation with ``fix viscous`` (F = -gamma v) at gamma = c x the
  grains' mean mass, c [1/s] our ``consolidate`` damping (near-critical for the packing's
  slowest mode), in chunks of 50 steps until PFC's ratio of the mean unbalanced force to
  the mean contact force is below ``consolidation_tol`` and the plate's stress is within
  ``consolidation_tol`` of the target (our ``relax`` criteria), or for a fixed number of
  steps (``consolidation_steps``);
- the push: the cone and its shaft, :func:`meshes.penetration.cone_penetrometer` (shaft
  ``depth + 3 cone_radius`` long, as ours) written as three STL meshes (the conical tip; the
  friction sleeve, 3.75 cone diameters of shaft above the cone, ISO 22476-1; the rest of the
  rod, if any), ``fix mesh/surface/stress`` (the force on each mesh is output), tip 0.1 grain
  radius above the consolidated grains within ``cone_radius + 2 radius`` of the axis (our
  ``lower_penetrator``), moved down at ``velocity`` by ``fix move/mesh linear`` for
  ``depth / velocity`` (``substeps`` steps per record); the viscous damping is off, the
  plate's servo keeps holding the stress. Every ``substeps`` steps: time, the z force on the
  tip, sleeve and rod meshes and the plate's; q_c = tip force / (pi R^2), f_s = sleeve
  force / (2 pi R L) (our ``cone_record``).

Where the peer differs from our run (the physics a LIGGGHTS user gets):

- the cone is a triangle mesh of radius ``cone_radius`` (sphere-triangle contacts, R* = the
  grain's radius); ours is a clump of ghost spheres of half a grain radius on that surface,
  whose envelope is the surface grown by their radius (a 6 mm cone among 1.5 mm grains is
  0.75 mm, 12 %, wider: it meets the grains sooner and pushes more of them) and whose
  contacts are sphere-sphere (R* = R r / (R + r), softer); q_c divides by pi R^2 in both;
- damping: LIGGGHTS' ``fix viscous`` is a force on the translational velocity only; ours
  scales the velocities AND spins by exp(-c dt) per step;
- the servo acts every step in both runs while consolidating; in our push it is updated once
  per block of ``substeps`` steps, here every step;
- the equilibrium ratio's denominator (mean contact force) is estimated from the pair
  virial (sum of f . r over contacts / (contacts x mean diameter): normal forces only, the
  branch taken as a diameter), ours sums the contact force magnitudes (with the viscous
  damping the ratio falls far below the tolerance here: the plate-stress criterion decides);
- the top plate is the servo mesh; ours is an infinite plane that only free grains touch
  (here meshes never touch each other either: the cone passes through the plate).

LIGGGHTS notes: one ``fix wall/gran`` of mesh type only (the plate's is replaced by one for
the plate and the cone meshes after consolidation); ``-screen none`` crashes the Debian
build when it reads an STL (its screen output goes to a NULL file), so the screen output is
captured instead.

CLI: ``python benchmarks/liggghts_chamber.py case.json [--cores N] [--consolidation-steps
K]`` runs the case (the benchmark's case JSON: ``{"parameters": {...}, ...}``) in a
directory beside it and writes ``case.liggghts.json`` (the keys our benchmark worker writes).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CHECK_EVERY = 50          # consolidation chunk [steps]: our relax's check_every
TIP, SLEEVE, ROD = "tip", "sleeve", "rod"


# ---- the parameters, the packing and the constants of our run --------------------------------
def _parameters(parameters):
    from coupling.apps.penetration.parameters import PenetrationParameters

    prm = parameters if isinstance(parameters, PenetrationParameters) else PenetrationParameters(**parameters)
    if prm.dim != 3 or not prm.vertical_stress > 0 or prm.shape != "cone":
        raise ValueError("the LIGGGHTS chamber is the 3D cone under a vertical stress "
                         f"(dim = 3, vertical_stress > 0, shape = 'cone'), got dim = {prm.dim}, "
                         f"vertical_stress = {prm.vertical_stress}, shape = {prm.shape!r}")
    return prm


def packing(prm):
    """Our chamber's grains: centres (n, 3) and radii (n,) exactly as ``DemPenetration``
    draws them."""
    from coupling.apps.penetration.coupled import grain_lattice

    W, H = prm.chamber_width, prm.chamber_depth
    rng = np.random.default_rng(prm.seed)
    return grain_lattice(prm, (-W / 2, -W / 2, -H), (W / 2, W / 2, 0.0), rng)


def constants(prm, x, radius) -> dict:
    """The numbers of our run the script needs: time step, consolidation damping c [1/s] and
    LIGGGHTS' gamma = c x mean mass, the plate servo's force, gain and speed limit."""
    from coupling.apps.penetration.chamber import packing_modulus
    from coupling.apps.penetration.coupled import dem_time_step

    dt = dem_time_step(prm, radius) * prm.dt_factor
    height = float(np.ptp(x[:, 2])) + 2 * prm.radius           # consolidate()'s
    damping = 2 * (np.pi * np.sqrt(packing_modulus(prm) / prm.density) / (2 * height))
    mass = prm.density * 4 / 3 * np.pi * radius**3
    rho = 0.6 * prm.density                                     # plate_servo()'s
    gain = 0.2 / (rho * np.sqrt(packing_modulus(prm) / rho))   # [m/s per Pa]
    v_max = max(prm.velocity, 0.1)
    area = prm.chamber_width**2
    block = prm.substeps * dt
    return {"dt": dt, "damping": damping, "gamma": damping * float(mass.mean()),
            "force": prm.vertical_stress * area, "area": area, "gain": gain, "v_max": v_max,
            "kp": gain * prm.vertical_stress / v_max,
            "push_steps": int(np.ceil(prm.depth / prm.velocity / block)) * prm.substeps}


# ---- files ----------------------------------------------------------------------------------
def write_stl(path: Path, points: np.ndarray, triangles: np.ndarray, name: str = "mesh") -> None:
    """ASCII STL of the triangles (m, 3) over points (n, 3)."""
    lines = [f"solid {name}"]
    for a, b, c in points[np.asarray(triangles)]:
        n = np.cross(b - a, c - a)
        n = n / (np.linalg.norm(n) or 1.0)
        lines += [f"  facet normal {n[0]:.9e} {n[1]:.9e} {n[2]:.9e}", "    outer loop"]
        lines += [f"      vertex {v[0]:.12e} {v[1]:.12e} {v[2]:.12e}" for v in (a, b, c)]
        lines += ["    endloop", "  endfacet"]
    lines.append(f"endsolid {name}")
    path.write_text("\n".join(lines) + "\n")


def cone_meshes(prm) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The cone penetrometer's surface (tip at the origin, axis up) split by triangle
    centroid into the conical tip, the friction sleeve (``SLEEVE_OVER_DIAMETER`` cone
    diameters above the cone's base) and the rod above it (absent for a short shaft)."""
    from coupling.apps.penetration.penetrators import SLEEVE_OVER_DIAMETER, tip_height
    from meshes.penetration import cone_penetrometer

    R = prm.cone_radius
    pts, tri = cone_penetrometer(3, radius=R, apex_deg=prm.apex_deg, shaft_length=prm.depth + 3 * R,
                                 h=max(R / 4, 0.5 * prm.radius))
    pts, tri = np.asarray(pts, float), np.asarray(tri, np.int64)
    zc = pts[tri, 2].mean(axis=1)
    h_cone = tip_height(prm)
    top = h_cone + SLEEVE_OVER_DIAMETER * 2 * R
    parts = {TIP: zc < h_cone, SLEEVE: (zc >= h_cone) & (zc <= top), ROD: zc > top}
    return {k: (pts, tri[m]) for k, m in parts.items() if m.any()}


def write_data(path: Path, x: np.ndarray, radius: np.ndarray, density: float, box) -> None:
    """LIGGGHTS data file (atom_style granular: id type diameter density x y z), 2 atom types
    (grains 1, walls 2)."""
    lo, hi = box
    head = [f"LIGGGHTS data file: calibration chamber, {len(x)} grains", "",
            f"{len(x)} atoms", "2 atom types", "",
            f"{lo[0]:.12e} {hi[0]:.12e} xlo xhi", f"{lo[1]:.12e} {hi[1]:.12e} ylo yhi",
            f"{lo[2]:.12e} {hi[2]:.12e} zlo zhi", "", "Atoms", ""]
    rows = [f"{i + 1} 1 {2 * r:.15e} {density:.9e} {p[0]:.15e} {p[1]:.15e} {p[2]:.15e}"
            for i, (p, r) in enumerate(zip(x, radius, strict=True))]
    path.write_text("\n".join(head + rows) + "\n")


SCRIPT = """\
# LIGGGHTS-PUBLIC 3.8 -- 3D virtual calibration chamber (peer of our DemPenetration),
# written by benchmarks/liggghts_chamber.py; grains {grains}, dt {dt:.9e} s
atom_style      granular
atom_modify     map array
boundary        f f f
newton          off
communicate     single vel yes
units           si
processors      * * 1

read_data       grains.data

neighbor        {skin:.9e} bin
neigh_modify    delay 0

# type 1 grains (and the cone), type 2 walls and plate: same E, nu; frictionless with grains
fix m1 all property/global youngsModulus peratomtype {E:.9e} {E:.9e}
fix m2 all property/global poissonsRatio peratomtype {nu:.9e} {nu:.9e}
fix m3 all property/global coefficientRestitution peratomtypepair 2 {e:.9e} {e:.9e} {e:.9e} {e:.9e}
fix m4 all property/global coefficientFriction peratomtypepair 2 {mu:.9e} 0.0 0.0 0.0

pair_style      gran model hertz tangential history limitForce on
pair_coeff      * *
timestep        {dt:.12e}

fix gravi all gravity {g:.9e} vector 0.0 0.0 -1.0

fix wx0 all wall/gran model hertz tangential history primitive type 2 xplane {xlo:.12e} limitForce on
fix wx1 all wall/gran model hertz tangential history primitive type 2 xplane {xhi:.12e} limitForce on
fix wy0 all wall/gran model hertz tangential history primitive type 2 yplane {xlo:.12e} limitForce on
fix wy1 all wall/gran model hertz tangential history primitive type 2 yplane {xhi:.12e} limitForce on
fix wz0 all wall/gran model hertz tangential history primitive type 2 zplane {zlo:.12e} limitForce on

# the top plate, servo-controlled at sigma_v W^2 along z (force on the plate up = -axis)
fix plate all mesh/surface/stress/servo file plate.stl type 2 com 0.0 0.0 {ztop:.12e} &
    ctrlPV force axis 0.0 0.0 -1.0 target_val {force:.9e} vel_max {v_max:.9e} kp {kp:.9e}
fix wplate all wall/gran model hertz tangential history mesh n_meshes 1 meshes plate limitForce on

fix integr all nve/sphere
fix damp all viscous {gamma:.9e}

# equilibrium: PFC's ratio of the mean unbalanced force to the mean contact force (this from
# the pair virial: sum f.r over contacts / (contacts x mean diameter))
variable fnet atom sqrt(fx*fx+fy*fy+fz*fz)
compute fmean all reduce ave v_fnet
compute sa all stress/atom pair
compute vir all reduce sum c_sa[1] c_sa[2] c_sa[3]
compute ca all contact/atom
compute nc all reduce sum c_ca
variable fcontact equal abs(c_vir[1]+c_vir[2]+c_vir[3])/(0.5*c_nc*{diameter:.9e}+1e-300)
variable ratio equal c_fmean/(v_fcontact+1e-300)
variable splate equal f_plate[3]/{area:.9e}
variable serr equal abs(v_splate-{stress:.9e})/{stress:.9e}
thermo_style    custom step atoms ke c_nc c_fmean v_fcontact v_ratio v_splate cpu
thermo          {check}
thermo_modify   norm no lost ignore

print "CONSOLIDATION START"
{consolidation}
print "CONSOLIDATION END ratio ${{ratio}} stress ${{splate}}"

# the push: no global damping; the cone's tip 0.1 grain radius above the grains near the axis
unfix damp
variable near atom (x*x+y*y)<{near2:.9e}
compute rad all property/atom radius
variable ztopatom atom v_near*(z+c_rad)-(1-v_near)*1e3
compute ztop all reduce max v_ztopatom
thermo_style    custom step atoms ke c_ztop v_splate cpu
run 0
variable ztip equal c_ztop+{gap:.9e}
variable z0 equal ${{ztip}}
print "CONE TIP ${{z0}}"
{cone_fixes}
# LIGGGHTS takes one mesh wall/gran fix: the plate's is replaced by one for all meshes (the
# plate is frictionless: no tangential history is lost)
unfix wplate
fix wmesh all wall/gran model hertz tangential history mesh n_meshes {n_mesh} meshes plate {cone_ids} limitForce on
{cone_moves}
variable step0 equal step
variable s0 equal ${{step0}}
variable t equal (step-${{s0}})*dt
variable depth equal (step-${{s0}})*dt*{velocity:.9e}
{force_vars}
fix out all print {substeps} "{print_line}" file cone.txt screen no title "# time depth {print_title} plate_fz"
thermo          {substeps}
thermo_style    custom step atoms ke v_splate {thermo_forces} cpu
print "PUSH START"
run {push_steps}
print "PUSH END"
"""


def write_case(parameters, directory, consolidation_steps: int | None = None) -> Path:
    """Write the LIGGGHTS case of ``parameters`` (a :class:`PenetrationParameters` or its
    dict) into ``directory``: ``grains.data``, ``plate.stl``, ``tip.stl``, ``sleeve.stl``
    (and ``rod.stl``), ``in.chamber`` and ``case.json`` (the constants used). Consolidation
    runs to our criteria (at most ``consolidation_max_steps``), or ``consolidation_steps``
    steps if given. Returns the input script's path."""
    prm = _parameters(parameters)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    x, radius = packing(prm)
    c = constants(prm, x, radius)
    W, H = prm.chamber_width, prm.chamber_depth
    ztop = float((x[:, 2] + radius).max())                     # our top_plate()
    from coupling.apps.penetration.penetrators import tip_height

    length = tip_height(prm) + prm.depth + 3 * prm.cone_radius   # the penetrometer's
    margin = 4 * prm.radius
    box = ((-W / 2 - margin, -W / 2 - margin, -H - margin),
           (W / 2 + margin, W / 2 + margin, ztop + prm.radius + length + margin))
    write_data(d / "grains.data", x, radius, prm.density, box)
    s = W / 2 + 2 * prm.radius
    write_stl(d / "plate.stl", np.array([[-s, -s, ztop], [s, -s, ztop], [s, s, ztop], [-s, s, ztop]]),
              np.array([[0, 1, 2], [0, 2, 3]]), "plate")
    meshes = cone_meshes(prm)
    for name, (pts, tri) in meshes.items():
        write_stl(d / f"{name}.stl", pts, tri, name)
    names = list(meshes)
    if consolidation_steps is None:
        chunks = int(np.ceil(prm.consolidation_max_steps / CHECK_EVERY))
        tol = prm.consolidation_tol
        consolidation = "\n".join([
            f"variable chunk loop {chunks}",
            "label consolidate",
            f"run {CHECK_EVERY} pre no post no",
            f'if "${{ratio}} < {tol:.9e} && ${{serr}} <= {tol:.9e}" then "jump SELF consolidated"',
            "next chunk",
            "jump SELF consolidate",
            'print "CONSOLIDATION NOT CONVERGED"',
            "label consolidated",
            "variable chunk delete"])
    else:
        consolidation = f"run {int(consolidation_steps)}"
    script = SCRIPT.format(
        grains=len(x), dt=c["dt"], skin=0.1 * 2 * prm.radius, E=prm.youngs_modulus, nu=prm.nu,
        e=prm.restitution, mu=prm.friction, g=prm.gravity, xlo=-W / 2, xhi=W / 2, zlo=-H, ztop=ztop,
        force=c["force"], v_max=c["v_max"], kp=c["kp"], gamma=c["gamma"], diameter=2 * float(radius.mean()),
        area=c["area"], stress=prm.vertical_stress, check=CHECK_EVERY, consolidation=consolidation,
        near2=(prm.cone_radius + 2 * prm.radius) ** 2, gap=0.1 * prm.radius,
        cone_fixes="\n".join(f"fix {n} all mesh/surface/stress file {n}.stl type 1 move 0.0 0.0 ${{z0}}"
                             for n in names),
        n_mesh=len(names) + 1, cone_ids=" ".join(names),
        cone_moves="\n".join(f"fix move_{n} all move/mesh mesh {n} linear 0.0 0.0 {-prm.velocity:.9e}"
                             for n in names),
        velocity=prm.velocity,
        force_vars="\n".join(f"variable fz_{n} equal f_{n}[3]" for n in names),
        substeps=prm.substeps,
        print_line=" ".join(["${t} ${depth}"] + [f"${{fz_{n}}}" for n in names] + ["${splate}"]),
        print_title=" ".join(f"fz_{n}" for n in names),
        thermo_forces=" ".join(f"f_{n}[3]" for n in names),
        push_steps=c["push_steps"])
    (d / "in.chamber").write_text(script)
    (d / "case.json").write_text(json.dumps({"parameters": {k: getattr(prm, k) for k in prm.__dataclass_fields__},
                                             "constants": c, "grains": len(x), "plate_z": ztop,
                                             "meshes": names}, indent=1))
    return d / "in.chamber"


# ---- running --------------------------------------------------------------------------------
def launcher(cores: int) -> list[str]:
    """The command prefix: ``liggghts`` alone on one core, else Open MPI's ``mpirun`` (the
    Debian package links Open MPI; the venv's ``mpiexec`` is MPICH's, for our own code)."""
    exe = shutil.which("liggghts")
    if exe is None:
        raise FileNotFoundError("liggghts is not installed (Debian: apt-get install liggghts)")
    if cores <= 1:
        return [exe]
    for cand in ("/usr/bin/mpirun.openmpi", "/usr/bin/orterun", "/usr/bin/mpirun"):
        if Path(cand).exists():
            return [cand, "--oversubscribe", "-np", str(cores), exe]
    raise FileNotFoundError("no Open MPI mpirun for LIGGGHTS (apt-get install openmpi-bin)")


def parse_log(text: str) -> dict:
    """Loop times and steps from a LIGGGHTS log: the consolidation's (every run between the
    CONSOLIDATION markers, including ``run 0``s after it up to the push) and the push's."""
    runs = [(m.start(), float(m.group(1)), int(m.group(2)))
            for m in re.finditer(r"Loop time of ([0-9.eE+-]+) on \d+ procs? for (\d+) steps", text)]
    push = re.search(r"^PUSH START", text, re.M)     # the print's output, not its echo
    if push is None:
        raise RuntimeError("LIGGGHTS log has no push (the run failed before it):\n" + text[-3000:])
    before = [r for r in runs if r[0] < push.start()]
    after = [r for r in runs if r[0] > push.start()]
    end = re.search(r"^CONSOLIDATION END ratio ([-+0-9.eE]+) stress ([-+0-9.eE]+)", text, re.M)
    version = re.search(r"LIGGGHTS \(Version ([^,)]+)", text)
    return {"setup_loop_s": sum(r[1] for r in before), "consolidation_steps": sum(r[2] for r in before),
            "push_loop_s": sum(r[1] for r in after), "push_steps": sum(r[2] for r in after),
            "converged": re.search(r"^CONSOLIDATION NOT CONVERGED", text, re.M) is None,
            "ratio": float(end.group(1)) if end else math.nan,
            "plate_stress": float(end.group(2)) if end else math.nan,
            "cone_tip_z": float(re.search(r"^CONE TIP ([-+0-9.eE]+)", text, re.M).group(1)),
            "liggghts_version": version.group(1).strip() if version else "unknown"}


def run_case(parameters, directory, cores: int = 1, consolidation_steps: int | None = None,
             nice: int = 0) -> dict:
    """Write and run the case in ``directory`` on ``cores`` MPI ranks; returns the record
    our benchmark worker writes (``grains``, ``setup_s`` and ``push_s``: wall time of the
    process up to the push, and the push's loop time; ``setup_cpu_s``/``push_cpu_s``: the
    process tree's CPU time split in the proportion of the loop times; ``dem_steps``/``steps``,
    ``dt``, ``depth``, ``q_c``, ``f_s``) plus the consolidation's outcome and the version."""
    from coupling.apps.penetration.penetrators import SLEEVE_OVER_DIAMETER

    prm = _parameters(parameters)
    d = Path(directory)
    script = write_case(prm, d, consolidation_steps)
    meta = json.loads((d / "case.json").read_text())
    cmd = ([shutil.which("nice") or "nice", "-n", str(nice)] if nice else []) + launcher(cores) + [
        "-in", script.name, "-log", "log.liggghts", "-nocite"]
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if cores > 1 and os.geteuid() == 0:     # Open MPI refuses root without these (containers)
        env |= {"OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run(cmd, cwd=d, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    log = (d / "log.liggghts").read_text() if (d / "log.liggghts").exists() else ""
    if proc.returncode:
        raise RuntimeError(f"liggghts failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
                           f"\n{log[-3000:]}")
    info = parse_log(log)
    table = np.loadtxt(d / "cone.txt", comments="#", ndmin=2)
    cols = ["time", "depth"] + [f"fz_{n}" for n in meta["meshes"]] + ["plate_fz"]
    data = dict(zip(cols, table.T, strict=True))
    R = prm.cone_radius
    L = SLEEVE_OVER_DIAMETER * 2 * R
    fz_tip = data["fz_tip"]
    fz_sleeve = data.get("fz_sleeve", np.zeros_like(fz_tip))
    # the force on the mesh along z: the grains push the cone up (positive, as our record)
    loops = info["setup_loop_s"] + info["push_loop_s"]
    share = info["push_loop_s"] / loops if loops > 0 else 0.0
    push_s = info["push_loop_s"]
    return {"grains": int(meta["grains"]), "cores": int(cores),
            "setup_s": wall - push_s, "push_s": push_s,
            "setup_cpu_s": cpu * (1 - share), "push_cpu_s": cpu * share, "wall_s": wall, "cpu_s": cpu,
            "setup_loop_s": info["setup_loop_s"],
            "consolidation_steps": info["consolidation_steps"], "consolidated": info["converged"],
            "consolidation_ratio": info["ratio"], "plate_stress": info["plate_stress"],
            "cone_tip_z": info["cone_tip_z"],
            "dem_steps": info["consolidation_steps"] + info["push_steps"], "steps": info["push_steps"],
            "dt": float(meta["constants"]["dt"]),
            "depth": data["depth"].tolist(), "q_c": (fz_tip / (np.pi * R**2)).tolist(),
            "f_s": (fz_sleeve / (2 * np.pi * R * L)).tolist(),
            "tip_force": fz_tip.tolist(), "plate_stress_push": (data["plate_fz"] / meta["constants"]["area"]).tolist(),
            "peak_memory_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
            "liggghts_version": info["liggghts_version"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("case", type=Path, help="the benchmark's case JSON ({'parameters': {...}})")
    parser.add_argument("--cores", type=int, default=1)
    parser.add_argument("--consolidation-steps", type=int, default=None,
                        help="a fixed consolidation (default: to our relax criteria)")
    parser.add_argument("--nice", type=int, default=0, help="run liggghts under nice -n NICE")
    args = parser.parse_args(argv)
    case = json.loads(args.case.read_text())
    work = args.case.with_suffix(".liggghts")
    out = run_case(case["parameters"], work, args.cores, args.consolidation_steps, args.nice)
    target = args.case.with_suffix(".liggghts.json")
    target.write_text(json.dumps(out))
    print(f"{out['grains']} grains: set-up {out['setup_s']:.1f} s ({out['consolidation_steps']} steps, "
          f"plate {out['plate_stress'] / 1e3:.4g} kPa), push {out['push_s']:.1f} s ({out['steps']} steps), "
          f"q_c at {out['depth'][-1] * 1e3:.3g} mm {out['q_c'][-1] / 1e3:.4g} kPa -> {target}")


if __name__ == "__main__":
    main()
