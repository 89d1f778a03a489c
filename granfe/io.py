"""Continuum output: VTX (ADIOS2 .bp) time series for ParaView and pyvista PNG renders.

Fields written: displacement u, micro-rotation phi (both at the degree of u), and the
unsymmetric force stress sigma and couple stress m (discontinuous Lagrange).
"""

from __future__ import annotations

from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import fem, plot
from dolfinx.io import VTXWriter

from granfe.problem import MicropolarProblem

__all__ = ["ContinuumWriter", "continuum_grid", "scalar_fields", "render_png"]


class ContinuumWriter:
    """VTX series ``<name>_fields.bp`` (u, phi) and ``<name>_stress.bp`` (sigma, m)."""

    def __init__(self, problem: MicropolarProblem, out_dir: str | Path, name: str = "continuum"):
        domain, gdim = problem.domain, problem.gdim
        k = problem.degree[0]
        self.problem = problem
        out_dir = Path(out_dir)
        if domain.comm.rank == 0:
            out_dir.mkdir(parents=True, exist_ok=True)
        domain.comm.barrier()
        self.u = fem.Function(fem.functionspace(domain, ("Lagrange", k, (gdim,))), name="u")
        phi_shape = () if gdim == 2 else (3,)
        self.phi = fem.Function(fem.functionspace(domain, ("Lagrange", k, phi_shape)), name="phi")
        kd = max(k - 1, 1)
        S = fem.functionspace(domain, ("Discontinuous Lagrange", kd, (gdim, gdim)))
        m_shape = (gdim,) if gdim == 2 else (3, 3)
        M = fem.functionspace(domain, ("Discontinuous Lagrange", kd, m_shape))
        self.sigma = fem.Function(S, name="sigma")
        self.m = fem.Function(M, name="couple_stress")
        sigma, m = problem.stress_expressions()
        self._sigma_expr = fem.Expression(sigma, S.element.interpolation_points)
        self._m_expr = fem.Expression(m, M.element.interpolation_points)
        self.paths = (out_dir / f"{name}_fields.bp", out_dir / f"{name}_stress.bp")
        self._writers = [VTXWriter(domain.comm, self.paths[0], [self.u, self.phi], engine="BP4"),
                         VTXWriter(domain.comm, self.paths[1], [self.sigma, self.m], engine="BP4")]

    def update(self) -> None:
        """Interpolate the problem's current state into the output functions."""
        w = self.problem.w
        self.u.interpolate(w.sub(0))
        self.phi.interpolate(w.sub(1))
        self.sigma.interpolate(self._sigma_expr)
        self.m.interpolate(self._m_expr)

    def write(self, t: float) -> None:
        self.update()
        for writer in self._writers:
            writer.write(t)

    def close(self) -> None:
        for writer in self._writers:
            writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def scalar_fields(problem: MicropolarProblem) -> dict[str, ufl.core.expr.Expr]:
    """Named scalar UFL fields for colouring: components, von Mises, magnitudes."""
    u, phi = ufl.split(problem.w)
    sigma, m = problem.stress_expressions()
    gdim = problem.gdim
    s = ufl.sym(sigma)
    dev = s - ufl.tr(s) / 3 * ufl.Identity(gdim) if gdim == 3 else s - ufl.tr(s) / 2 * ufl.Identity(2)
    fields = {
        "u_magnitude": ufl.sqrt(ufl.inner(u, u)),
        "von_mises": ufl.sqrt(1.5 * ufl.inner(dev, dev)),
        "couple_stress_magnitude": ufl.sqrt(ufl.inner(m, m)),
        "phi_z": phi if gdim == 2 else phi[2],
    }
    axes = "xyz"
    for i in range(gdim):
        fields[f"u_{axes[i]}"] = u[i]
        for j in range(gdim):
            fields[f"sigma_{axes[i]}{axes[j]}"] = sigma[i, j]
    if gdim == 2:
        fields["m_zx"], fields["m_zy"] = m[0], m[1]
    return fields


def continuum_grid(problem: MicropolarProblem, field: str = "von_mises"):
    """The body as a pyvista grid with point data ``u`` (3 components) and ``field``.

    Collective: every rank sends its part to rank 0; returns the grid on rank 0, None elsewhere.
    """
    import pyvista

    fields = scalar_fields(problem)
    if field not in fields:
        raise ValueError(f"unknown field {field!r}; choose one of {sorted(fields)}")
    domain, gdim = problem.domain, problem.gdim
    V1 = fem.functionspace(domain, ("Lagrange", 1, (gdim,)))
    S1 = fem.functionspace(domain, ("Lagrange", 1))
    u1, s1 = fem.Function(V1), fem.Function(S1)
    u1.interpolate(problem.w.sub(0))
    s1.interpolate(fem.Expression(fields[field], S1.element.interpolation_points))
    topology, cell_types, x = plot.vtk_mesh(V1)
    parts = domain.comm.gather((topology, cell_types, x, u1.x.array.reshape(-1, gdim).copy(),
                                s1.x.array.copy()), root=0)
    if domain.comm.rank != 0:
        return None
    grids = []
    for top, ct, pts, disp, val in parts:
        g = pyvista.UnstructuredGrid(top, ct, pts)
        d3 = np.zeros((len(pts), 3))
        d3[:, :gdim] = disp
        g.point_data["u"] = d3
        g.point_data[field] = val
        grids.append(g)
    return grids[0] if len(grids) == 1 else pyvista.merge(grids)


def render_png(problem: MicropolarProblem, path: str | Path, field: str = "von_mises",
               warp: float | None = None, title: str | None = None, clim=None,
               box: tuple[float, ...] | None = None, overlay=None) -> Path | None:
    """Render the (optionally warped) body coloured by a named scalar field to a PNG.

    Collective (see :func:`continuum_grid`); rank 0 renders with pyvista offscreen.
    ``warp`` scales the displacement (None: 10% of the body size at the largest
    displacement; 0: undeformed). ``box = (xmin, xmax, ymin, ymax[, zmin, zmax])`` zooms
    to a region. ``overlay(plotter, warp)`` may add more actors (e.g. particles).
    Returns the path on rank 0.
    """
    import pyvista

    pyvista.OFF_SCREEN = True
    grid = continuum_grid(problem, field)
    if grid is None:
        return None
    size = float(np.max(np.ptp(grid.points, axis=0)))
    umax = float(np.max(np.linalg.norm(grid.point_data["u"], axis=1)))
    if warp is None:
        warp = 0.1 * size / umax if umax > 0 else 0.0
    shown = grid.warp_by_vector("u", factor=warp) if warp else grid
    if box is not None:
        bounds = list(box) + [-1.0, 1.0] * (len(box) == 4)
        shown = shown.clip_box(bounds, invert=False)
    plotter = pyvista.Plotter(off_screen=True, window_size=(1200, 900))
    plotter.add_mesh(shown, scalars=field, cmap="viridis", clim=clim, show_edges=False,
                     scalar_bar_args={"title": field, "vertical": True})
    if overlay is not None:
        overlay(plotter, warp)
    plotter.add_text(title or f"{field} (displacement x {warp:.3g})", font_size=12)
    if problem.gdim == 2:
        plotter.view_xy()
    else:
        plotter.view_isometric()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plotter.screenshot(str(path))
    plotter.close()
    return path
