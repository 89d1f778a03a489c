"""Particle-centroid basis evaluation and the nodal L2 projection (seed 001 eq. 74-90).

Tolerances: exactness (~1e-10) for fields inside the discrete space; the MPI test
compares a 2-rank run with a serial (COMM_SELF) run of the same problem to round-off.
"""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import basix.ufl
import dolfinx
import numpy as np
import pytest
from dolfinx import fem, mesh

from coupling.locate import PointsOutsideMesh, affine_maps, owner_ranks, reference_coordinates, relocate
from coupling.operators import FieldBasis, NodalProjection, SingularProjection


def mixed_space(comm, n=4):
    msh = mesh.create_unit_square(comm, n, n, diagonal=mesh.DiagonalType.crossed)
    cell = msh.basix_cell()
    el = basix.ufl.mixed_element(
        [basix.ufl.element("Lagrange", cell, 2, shape=(2,)), basix.ufl.element("Lagrange", cell, 1)]
    )
    return fem.functionspace(msh, el)


def smooth_state(V):
    """A partition-independent state: smooth non-polynomial u and phi interpolated into V."""
    w = fem.Function(V)
    w.sub(0).interpolate(lambda x: np.vstack([np.sin(3 * x[0]) * x[1], np.cos(2 * x[1]) + x[0]]))
    w.sub(1).interpolate(lambda x: np.exp(x[0] - x[1]))
    w.x.scatter_forward()
    return w


def all_points(n=1500, seed=7):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, size=(n, 2))


def my_points(V, pts):
    """Every rank holds all points; keep those whose cell this rank owns (and their ids)."""
    owners = owner_ranks(V.mesh, pts)
    mine = np.flatnonzero(owners == V.mesh.comm.rank)
    return pts[mine], mine


def eval_at(w_sub, V, pts):
    """Independent route: Function.eval at the points, cell by cell."""
    msh = V.mesh
    tree = dolfinx.geometry.bb_tree(msh, msh.topology.dim)
    x3 = np.c_[pts, np.zeros(len(pts))]
    cand = dolfinx.geometry.compute_collisions_points(tree, x3)
    cells = dolfinx.geometry.compute_colliding_cells(msh, cand, x3)
    cell_of = np.array([cells.links(i)[0] for i in range(len(pts))], dtype=np.int32)
    return w_sub.eval(x3, cell_of)


@pytest.mark.mpi
@pytest.mark.parametrize("sub, value_size", [(0, 2), (1, 1)])
def test_interpolation_matches_function_eval(sub, value_size):
    V = mixed_space(MPI.COMM_WORLD)
    w = smooth_state(V)
    pts, _ = my_points(V, all_points())
    basis = FieldBasis.build(V, pts, sub=sub)
    q = basis.interpolate(w)
    assert q.shape == (len(pts), value_size)
    ref = eval_at(w.sub(sub), V, pts).reshape(len(pts), value_size)
    assert np.allclose(q, ref, rtol=0, atol=1e-12)
    # the distributed PETSc matrix and the local CSR agree
    y = basis.matrix.createVecLeft()
    basis.matrix.mult(w.x.petsc_vec, y)
    assert np.allclose(y.getArray(), q.ravel(), atol=1e-13)


@pytest.mark.mpi
@pytest.mark.parametrize("shape", [(), (2,)])
def test_plain_space_is_its_own_field(shape):
    """sub = None: the basis of a plain (not mixed) space, as the pore fluid's porosity uses."""
    msh = mesh.create_unit_square(MPI.COMM_WORLD, 4, 4, diagonal=mesh.DiagonalType.crossed)
    V = fem.functionspace(msh, ("Lagrange", 2, shape))
    w = fem.Function(V)
    w.interpolate(lambda x: np.sin(3 * x[0]) * x[1] if shape == () else
                  np.vstack([np.sin(3 * x[0]) * x[1], np.exp(x[0] - x[1])]))
    w.x.scatter_forward()
    pts, _ = my_points(V, all_points())
    q = FieldBasis.build(V, pts).interpolate(w)
    ref = eval_at(w, V, pts).reshape(q.shape)
    assert np.allclose(q, ref, rtol=0, atol=1e-12)


def prescribed_dofs(basis, xmin):
    """Owned dofs of the field whose node lies at x >= xmin (the prescribed overlap nodes)."""
    imap, bs = basis.V.dofmap.index_map, basis.V.dofmap.bs
    owned = basis.dofs < imap.size_local * bs
    return basis.dofs[owned & (basis.dof_coordinates[:, 0] >= xmin)]


@pytest.mark.mpi
@pytest.mark.parametrize("sub", [0, 1])
def test_projection_reproduces_fe_field(sub):
    V = mixed_space(MPI.COMM_WORLD)
    exact = smooth_state(V)
    pts, _ = my_points(V, all_points())
    basis = FieldBasis.build(V, pts, sub=sub)
    q = basis.interpolate(exact)  # particle motion that an FE field can represent exactly

    prescribed = prescribed_dofs(basis, 0.5)
    assert MPI.COMM_WORLD.allreduce(prescribed.size) > 0
    trial = exact.copy()
    trial.x.array[prescribed] += 1.0  # wrong prescribed values: the projection must restore them
    proj = NodalProjection(basis, prescribed)
    proj.apply(q, trial)
    err = np.abs(trial.x.array - exact.x.array).max(initial=0.0)
    assert MPI.COMM_WORLD.allreduce(err, op=MPI.MAX) < 1e-10


def test_singular_projection_names_dofs():
    V = mixed_space(MPI.COMM_WORLD)
    pts = all_points()
    pts = pts[pts[:, 0] < 0.4]  # no particles over the right part
    pts, _ = my_points(V, pts)
    basis = FieldBasis.build(V, pts, sub=1)
    prescribed = prescribed_dofs(basis, 0.0)
    with pytest.raises(SingularProjection, match="no particle in their support"):
        NodalProjection(basis, prescribed)
    # the regularised projection solves and leaves unsupported dofs near their least-norm value
    w = smooth_state(V)
    proj = NodalProjection(basis, prescribed, regularization=1e-8)
    vals = proj.project(basis.interpolate(w), w)
    assert np.all(np.isfinite(vals))


def test_points_outside_mesh_are_named():
    V = mixed_space(MPI.COMM_WORLD)
    pts = np.array([[0.5, 0.5], [1.5, 0.2]])
    with pytest.raises(PointsOutsideMesh, match=r"outside the FE mesh.*#1"):
        owner_ranks(V.mesh, pts)


@pytest.mark.mpi
def test_parallel_equals_serial():
    """Interpolated particle values and projected dofs: 2 ranks == COMM_SELF to round-off."""
    comm = MPI.COMM_WORLD
    pts_all = all_points(800, seed=3)

    def run(c):
        V = mixed_space(c)
        exact = smooth_state(V)
        pts, ids = my_points(V, pts_all)
        basis = FieldBasis.build(V, pts, sub=0)
        q = basis.interpolate(exact)
        prescribed = prescribed_dofs(basis, 0.5)
        trial = exact.copy()
        trial.x.array[prescribed] = 0.0
        NodalProjection(basis, prescribed).apply(q + 1e-3 * np.sin(pts), trial)
        # probe the projected field at fixed points (partition independent)
        probe = np.array([[0.6, 0.3], [0.9, 0.9], [0.75, 0.55]])
        pp, pid = my_points(V, probe)
        vals = np.zeros((3, 2))
        if len(pp):
            vals[pid] = FieldBasis.build(V, pp, sub=0).interpolate(trial)
        else:
            FieldBasis.build(V, pp, sub=0)  # collective
        qs = np.zeros((len(pts_all), 2))
        qs[ids] = q
        return c.allreduce(qs), c.allreduce(vals)

    q_par, v_par = run(comm)
    q_ser, v_ser = run(MPI.COMM_SELF)
    assert np.allclose(q_par, q_ser, rtol=0, atol=1e-13)
    assert np.allclose(v_par, v_ser, rtol=0, atol=1e-11)


def toward_centroid(V, basis, pts, fraction=0.3):
    """Points moved part of the way to their cell's centroid: same cell, new basis values."""
    geo = V.mesh.geometry
    centroid = geo.x[geo.dofmaps[0][basis.cells]].mean(axis=1)[:, :2]
    return pts + fraction * (centroid - pts)


def moved_on_same_rank(V, pts_all, shift):
    """Shifted points that stay inside the square and on the rank that held them."""
    moved = np.clip(pts_all + shift, 1e-3, 1 - 1e-3)
    keep = owner_ranks(V.mesh, pts_all) == owner_ranks(V.mesh, moved)  # same on every rank
    return pts_all[keep], moved[keep]


@pytest.mark.mpi
@pytest.mark.parametrize("sub", [0, 1])
def test_update_equals_fresh_build(sub):
    """Moving particles inside their cells refactorises M's values only; moving them across
    cells rebuilds the sparsity; both give the fresh build's N and D^ to round-off."""
    V = mixed_space(MPI.COMM_WORLD)
    comm = V.mesh.comm
    w = smooth_state(V)
    rng = np.random.default_rng(11)
    before, after = moved_on_same_rank(V, all_points(600, seed=5),
                                       0.04 * rng.standard_normal((600, 2)))
    pts, ids = my_points(V, before)
    basis = FieldBasis.build(V, pts, sub=sub)
    prescribed = prescribed_dofs(basis, 0.5)
    proj = NodalProjection(basis, prescribed)
    q_values = np.sin(7 * pts).reshape(-1)[: len(pts) * basis.value_size].reshape(len(pts), -1)

    def agrees_with_fresh(new_pts):
        fresh = FieldBasis.build(V, new_pts, sub=sub)
        fresh_proj = NodalProjection(fresh, prescribed)
        err_n = np.abs(basis.interpolate(w) - fresh.interpolate(w)).max(initial=0.0)
        y, y0 = basis.matrix.createVecLeft(), fresh.matrix.createVecLeft()
        basis.matrix.mult(w.x.petsc_vec, y)
        fresh.matrix.mult(w.x.petsc_vec, y0)
        err_petsc = np.abs(y.getArray() - y0.getArray()).max(initial=0.0)
        d, d0 = proj.project(q_values, w), fresh_proj.project(q_values, w)
        scale = comm.allreduce(np.abs(d0).max(initial=0.0), op=MPI.MAX)
        err_d = np.abs(d - d0).max(initial=0.0) / scale
        return comm.allreduce(max(err_n, err_petsc, err_d), op=MPI.MAX)

    inside = toward_centroid(V, basis, pts)
    assert basis.update(inside) == 0
    assert proj.update() is False and proj.value_updates == 1 and proj.rebuilds == 1
    assert agrees_with_fresh(inside) < 1e-12

    moved = after[ids]
    assert basis.update(moved) > 0
    assert proj.update() is True and proj.rebuilds == 2
    assert agrees_with_fresh(moved) < 1e-12


@pytest.mark.parametrize("dim", [2, 3])
def test_affine_maps_pull_back_as_the_solve(dim):
    """The inverse Jacobians taken once (affine_maps) pull points back as the per-call solve
    does, to round-off, and relocate with them finds the same cells (moved points included);
    a quadrilateral mesh has none."""
    comm = MPI.COMM_SELF
    msh = mesh.create_unit_square(comm, 3, 4) if dim == 2 else mesh.create_unit_cube(comm, 2, 3, 2)
    rng = np.random.default_rng(3)
    x = np.zeros((400, 3))
    x[:, :dim] = rng.uniform(0.0, 1.0, (400, dim))
    V = fem.functionspace(msh, ("Lagrange", 1))
    cells = FieldBasis.build(V, x[:, :dim]).cells
    maps = affine_maps(msh)
    np.testing.assert_allclose(reference_coordinates(msh, x, cells, maps),
                               reference_coordinates(msh, x, cells), atol=1e-13)
    moved = np.clip(x + 0.05 * rng.standard_normal(x.shape) * (np.arange(3) < dim), 0, 1)
    fast, slow = relocate(msh, moved, cells, maps=maps), relocate(msh, moved, cells)
    assert fast[2].any()
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-13)
    assert affine_maps(mesh.create_unit_square(comm, 2, 2, mesh.CellType.quadrilateral)) is None


@pytest.mark.mpi
@pytest.mark.parametrize("dim", [2, 3])
def test_the_walk_finds_the_cells_the_tree_finds(dim):
    """relocate's walk through the facets (with affine_maps) places moved points in the
    cells the bounding-box search finds (points off the facets: one cell each), X to
    round-off, the same points lost (moved out of the mesh), on a refined mesh where points
    cross up to ~6 elements (longer ways fall back to the search); every rank's own cells
    (2 ranks: points that enter a ghost cell are lost alike)."""
    comm = MPI.COMM_WORLD
    n = 16 if dim == 2 else 6
    msh = mesh.create_unit_square(comm, n, n) if dim == 2 else mesh.create_unit_cube(comm, n, n, n)
    maps = affine_maps(msh)
    owned = msh.topology.index_map(msh.topology.dim).size_local
    rng = np.random.default_rng(7 + comm.rank)
    cells = rng.integers(0, owned, 600).astype(np.int32)
    v = msh.geometry.x[msh.geometry.dofmaps[0][cells]]
    w = rng.dirichlet(np.ones(dim + 1), len(cells))
    x = np.einsum("na,nai->ni", w, v)          # one point inside each cell
    for scale in (0.2 / n, 1.0 / n, 4.0 / n):
        moved = x + scale * rng.standard_normal(x.shape) * (np.arange(3) < dim)
        walk, tree = relocate(msh, moved, cells, maps=maps), relocate(msh, moved, cells)
        assert np.array_equal(walk[3], tree[3])
        keep = ~walk[3]
        assert np.array_equal(walk[0][keep], tree[0][keep]) and np.array_equal(walk[2], tree[2])
        np.testing.assert_allclose(walk[1][keep], tree[1][keep], atol=1e-12)
        assert walk[2].any()
    outside = x.copy()
    outside[:5, 0] += 2.0
    assert relocate(msh, outside, cells, maps=maps)[3][:5].all()


def test_update_refuses_particles_that_left():
    V = mixed_space(MPI.COMM_WORLD)
    pts, _ = my_points(V, all_points(50))
    basis = FieldBasis.build(V, pts, sub=1)
    with pytest.raises(ValueError, match=f"the same {len(pts)} particles, got 3"):
        basis.update(pts[:3])
    away = pts.copy()
    away[:1] += 2.0
    with pytest.raises(PointsOutsideMesh, match="left the cells of their rank"):
        basis.update(away)


@pytest.mark.mpi
def test_interface_update_positions_equals_fresh_interface():
    """CouplingInterface.update_positions: in-cell moves, cell changes and (under MPI) rank
    changes all give the ghost motion and projected dofs of a fresh interface."""
    from coupling.interface import CouplingInterface
    from coupling.regions import Box, CouplingRegions
    from dem.bonded import hexagonal_lattice
    from granfe.materials import MicropolarMaterial
    from granfe.problem import MicropolarProblem

    comm = MPI.COMM_WORLD
    domain = mesh.create_unit_square(comm, 8, 8)
    material = MicropolarMaterial(lam=1e6, mu=1e6, kappa=1e5, gamma=1e2)
    regions = CouplingRegions(Box((0.3, 0.3), (0.7, 0.7)), ghost_width=0.06, handshake=0.1)
    x = hexagonal_lattice((0.2, 0.2), (0.8, 0.8), 0.0125) + np.array([1.3e-3, 0.7e-3, 0.0])
    kinds = regions.particle_kinds(x)
    x, kinds = x[kinds >= 0], kinds[kinds >= 0]
    rng = np.random.default_rng(2)
    u, theta = rng.standard_normal((len(x), 3)) * 1e-3, rng.standard_normal(len(x)) * 1e-3

    def problem(tag):
        p = MicropolarProblem(domain, material, degree=(2, 1), prefix=f"upd_{tag}_")
        p.w.sub(0).interpolate(lambda y: np.vstack([np.sin(3 * y[0]) * y[1], y[0] ** 2]))
        p.w.sub(1).interpolate(lambda y: np.exp(y[0] - y[1]))
        p.w.x.scatter_forward()
        return p

    def outputs(iface):
        ug, tg = iface.ghost_motion()
        return ug, tg, iface.project(u, theta)

    iface = CouplingInterface(problem("moving"), x, kinds, regions)
    moves = [("inside cells", x + 1e-7 * rng.standard_normal(x.shape) * [1, 1, 0]),
             ("across cells", x + 0.02 * rng.standard_normal(x.shape) * [1, 1, 0]),
             ("shifted", x + np.array([0.12, -0.05, 0.0]))]
    for k, (name, xk) in enumerate(moves):
        counts = iface.update_positions(xk)
        fresh = CouplingInterface(problem(f"fresh{k}"), xk, kinds, regions)
        for a, b in zip(outputs(iface), outputs(fresh), strict=True):
            err = comm.allreduce(np.abs(a - b).max(initial=0.0), op=MPI.MAX)
            scale = comm.allreduce(np.abs(b).max(initial=0.0), op=MPI.MAX)
            assert err <= 1e-11 * scale, (name, err, scale)
        if name == "inside cells":
            assert counts["changed_cell"] == 0 and not counts["pattern_rebuilt"]
        if name == "across cells":
            assert counts["pattern_rebuilt"]
            assert counts["changed_cell"] > 0 or counts["full_rebuild"]
        assert counts["full_rebuild"] == (counts["changed_rank"] > 0)
    assert iface.update_counts["updates"] == 3
