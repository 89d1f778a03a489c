"""Particle output: VTU frames with a PVD time series, offscreen PNG renders, ``.npz`` states.

Frames are meshio VTU files with one vertex cell per particle; every point-data array has
``n`` rows (scalars (n,), vectors (n, 3)). ParaView opens the ``.pvd`` series; use the
"Point Gaussian" representation or a Glyph filter scaled by ``radius``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

__all__ = ["ParticleWriter", "load_state", "read_contact_frame", "read_vtu", "render_png", "save_state",
           "write_contact_frame", "write_vtu"]


def _check_arrays(x, radius, point_data) -> tuple[np.ndarray, np.ndarray, dict]:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x must have shape (n, 3), got {x.shape}")
    n = x.shape[0]
    radius = np.asarray(radius, dtype=np.float64)
    if radius.shape != (n,):
        raise ValueError(f"radius must have shape ({n},), got {radius.shape}")
    data = {"radius": radius}
    for name, a in point_data.items():
        if a is None:
            continue
        a = np.asarray(a)
        if a.shape[0] != n:
            raise ValueError(f"point data {name!r} must have {n} rows, got shape {a.shape}")
        data[name] = a.astype(np.float64) if a.dtype.kind == "f" else a
    return x, radius, data


def write_vtu(path, x, radius, **point_data) -> Path:
    """Write one frame: points ``x`` (n, 3) [m], ``radius`` (n,) [m] and any (n, ...) arrays
    (e.g. ``velocity``, ``omega``, ``force``, ``kind``)."""
    import meshio

    x, radius, data = _check_arrays(x, radius, point_data)
    cells = [("vertex", np.arange(len(x), dtype=np.int64).reshape(-1, 1))]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, meshio.Mesh(x, cells, point_data=data), file_format="vtu")
    return path


def read_vtu(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read a frame written by `write_vtu`: returns x (n, 3), radius (n,), other point data."""
    import meshio

    mesh = meshio.read(path)
    data = dict(mesh.point_data)
    if "radius" not in data:
        raise ValueError(f"{path}: no 'radius' point data; not a particle frame")
    return np.asarray(mesh.points, dtype=np.float64), data.pop("radius"), data


class ParticleWriter:
    """Time series of VTU frames ``out_dir/name_NNNNNN.vtu`` and the collection ``name.pvd``.

    The ``.pvd`` file is rewritten after every frame, so a run stopped early still has a
    readable series; `close` writes it a final time.
    """

    def __init__(self, out_dir, name: str = "particles"):
        if not name or os.sep in name:
            raise ValueError(f"name must be a non-empty file stem without '{os.sep}', got {name!r}")
        self.out_dir = Path(out_dir)
        self.name = name
        self.frames: list[tuple[float, str]] = []
        self.out_dir.mkdir(parents=True, exist_ok=True)

    @property
    def pvd_path(self) -> Path:
        return self.out_dir / f"{self.name}.pvd"

    def write(self, t: float, x, radius, **point_data) -> Path:
        """Write the frame at time ``t`` [s] (strictly after the previous frame)."""
        if self.frames and not t > self.frames[-1][0]:
            raise ValueError(f"t must increase: got {t!r} after {self.frames[-1][0]!r}")
        fname = f"{self.name}_{len(self.frames):06d}.vtu"
        path = write_vtu(self.out_dir / fname, x, radius, **point_data)
        self.frames.append((float(t), fname))
        self._write_pvd()
        return path

    def _write_pvd(self):
        root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
        coll = ET.SubElement(root, "Collection")
        for t, fname in self.frames:
            ET.SubElement(coll, "DataSet", timestep=repr(t), group="", part="0", file=fname)
        ET.indent(root)
        ET.ElementTree(root).write(self.pvd_path, xml_declaration=True, encoding="utf-8")

    def close(self) -> Path:
        self._write_pvd()
        return self.pvd_path

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def save_state(path, **arrays) -> Path:
    """Save named arrays (and scalars such as ``t``) to an uncompressed ``.npz``."""
    if not arrays:
        raise ValueError("save_state needs at least one named array")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: np.asarray(v) for k, v in arrays.items()})
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def load_state(path) -> dict[str, np.ndarray]:
    """Load a `save_state` file into a dict (0-d arrays come back as Python scalars)."""
    with np.load(path, allow_pickle=False) as f:
        return {k: (f[k].item() if f[k].ndim == 0 else f[k].copy()) for k in f.files}


def render_png(path, x, radius, scalars=None, *, scalar_name: str = "value",
               cmap: str = "viridis", window_size=(800, 600), resolution: int = 12,
               view: str | None = None, title: str | None = None) -> Path:
    """Render particles as spheres (glyphs scaled by radius) offscreen into a PNG.

    Args:
        x: (n, 3) centres [m]; radius: (n,) [m]; scalars: (n,) colour values or None.
        view: ``"xy"`` (default when all z are equal, i.e. 2D disks), ``"xz"`` or
            ``"iso"`` (default in 3D).
    """
    import pyvista

    pyvista.OFF_SCREEN = True
    x, radius, data = _check_arrays(x, radius, {scalar_name: scalars})
    if len(x) == 0:
        raise ValueError("render_png needs at least one particle")
    cloud = pyvista.PolyData(x)
    cloud["radius"] = 2.0 * radius  # the glyph sphere has unit diameter
    if scalars is not None:
        cloud[scalar_name] = np.asarray(data[scalar_name], dtype=np.float64)
    glyphs = cloud.glyph(scale="radius", orient=False,
                         geom=pyvista.Sphere(radius=0.5, theta_resolution=resolution,
                                             phi_resolution=resolution))
    plotter = pyvista.Plotter(off_screen=True, window_size=list(window_size))
    plotter.set_background("white")
    kw = dict(scalars=scalar_name, cmap=cmap) if scalars is not None else dict(color="tan")
    plotter.add_mesh(glyphs, smooth_shading=True, **kw)
    if view is None:
        view = "xy" if np.ptp(x[:, 2]) == 0 else "iso"
    {"xy": plotter.view_xy, "xz": plotter.view_xz, "iso": plotter.view_isometric}[view]()
    if title:
        plotter.add_title(title, font_size=10, color="black")
    plotter.reset_camera()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def write_contact_frame(path, sim, step: int | None = None) -> Path:
    """Save what the stress measures need from a `dem.Simulation` now: positions,
    velocities, radii, masses, touching pairs and their forces (force on i by j), time."""
    pairs, force = sim.contact_forces()
    p = sim.p
    return save_state(path, x=p.x, v=p.v, radius=p.radius, mass=p.mass, kind=p.kind,
                      pairs=pairs, force=force, t=np.array(sim.time),
                      step=np.array(sim.nsteps if step is None else step))


def read_contact_frame(path) -> dict:
    """A frame written by `write_contact_frame` (arrays; ``t`` and ``step`` as scalars)."""
    data = load_state(path)
    missing = {"x", "v", "radius", "mass", "pairs", "force", "t", "step"} - set(data)
    if missing:
        raise ValueError(f"{path} is not a contact frame: missing {sorted(missing)}")
    data["t"], data["step"] = float(data["t"]), int(data["step"])
    return data
