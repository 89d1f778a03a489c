"""Continuum output: VTX (ADIOS2 .bp) time series for ParaView and pyvista PNG renders,
over any model's fields, stresses and history variables."""

from __future__ import annotations

from pathlib import Path

import dolfinx_solver  # noqa: F401

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem, plot
from dolfinx.io import VTXWriter

from granfe.problem import ContinuumProblem

__all__ = ["ContinuumWriter", "continuum_grid", "scalar_fields", "render_png"]


class ContinuumWriter:
    """VTX series of a problem's fields and stresses.

    ``<name>_fields.bp``: every field of the model at the degree of its first field
    (micropolar: u, phi); ``<name>_stress.bp``: its stress measures (micropolar: sigma,
    couple_stress), discontinuous Lagrange one degree lower (at least 1), or cell averages
    over the quadrature points for a model with history; ``<name>_state.bp``: the history
    variables as cell averages, for a model that has them. Functions are attributes by name
    (``writer.u``, ``writer.sigma``).
    """

    def __init__(self, problem: ContinuumProblem, out_dir: str | Path, name: str = "continuum"):
        domain = problem.domain
        k = problem.degree[0]
        self.problem = problem
        out_dir = Path(out_dir)
        if domain.comm.rank == 0:
            out_dir.mkdir(parents=True, exist_ok=True)
        domain.comm.barrier()
        self.fields = {}
        for f in problem.fields:
            self.fields[f.name] = fem.Function(fem.functionspace(domain, ("Lagrange", k, f.shape)),
                                               name=f.name)
        stresses = problem.stresses()
        self.stresses, self._stress_exprs = {}, {}
        averaged = bool(problem.state)
        for sname, expr in stresses.items():
            shape = ufl.shape(expr)
            if averaged:
                S = fem.functionspace(domain, ("Discontinuous Lagrange", 0, shape))
                Q = fem.functionspace(domain, basix.ufl.quadrature_element(
                    domain.basix_cell(), value_shape=shape, degree=problem.state.degree))
                self._stress_exprs[sname] = (fem.Expression(expr, Q.element.interpolation_points,
                                                            jit_options=problem.jit_options),
                                             fem.Function(Q))
            else:
                S = fem.functionspace(domain, ("Discontinuous Lagrange", max(k - 1, 1), shape))
                self._stress_exprs[sname] = (fem.Expression(expr, S.element.interpolation_points,
                                                            jit_options=problem.jit_options), None)
            self.stresses[sname] = fem.Function(S, name=sname)
        self.state = {}
        for sname, q in problem.state.committed.items():
            shape = q.function_space.value_shape
            S = fem.functionspace(domain, ("Discontinuous Lagrange", 0, shape))
            self.state[sname] = fem.Function(S, name=sname)
        for attr, f in {**self.fields, **self.stresses}.items():
            setattr(self, attr, f)
        self.paths = [out_dir / f"{name}_fields.bp", out_dir / f"{name}_stress.bp"]
        groups = [list(self.fields.values()), list(self.stresses.values())]
        if self.state:
            self.paths.append(out_dir / f"{name}_state.bp")
            groups.append(list(self.state.values()))
        self.paths = tuple(self.paths)
        self._writers = [VTXWriter(domain.comm, path, group, engine="BP4")
                         for path, group in zip(self.paths, groups, strict=True)]

    def update(self) -> None:
        """Interpolate the problem's current state into the output functions."""
        w = self.problem.w
        for i, f in enumerate(self.fields.values()):
            f.interpolate(w.sub(i))
        for sname, (expr, quad) in self._stress_exprs.items():
            if quad is None:
                self.stresses[sname].interpolate(expr)
            else:
                quad.interpolate(expr)
                _cell_average(quad, self.stresses[sname])
        for sname, f in self.state.items():
            _cell_average(self.problem.state.committed[sname], f)

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


def _cell_average(quad: fem.Function, dg0: fem.Function) -> None:
    """Mean over each cell's quadrature points of a quadrature function, into DG0."""
    Q, S = quad.function_space, dg0.function_space
    bs = Q.dofmap.index_map_bs
    values = quad.x.array.reshape(-1, bs)[Q.dofmap.list].mean(axis=1)
    dg0.x.array.reshape(-1, bs)[S.dofmap.list[:, 0]] = values
    dg0.x.scatter_forward()


def scalar_fields(problem: ContinuumProblem) -> dict[str, ufl.core.expr.Expr]:
    """Named scalar UFL fields for colouring (the model's: components, von Mises, ...)."""
    return problem.model.plot_fields(problem.split(problem.w), problem.state.committed)


def continuum_grid(problem: ContinuumProblem, field: str = "von_mises"):
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


def render_png(problem: ContinuumProblem, path: str | Path, field: str = "von_mises",
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
