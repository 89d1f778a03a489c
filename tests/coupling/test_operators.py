"""Particle-centroid basis evaluation and the nodal L2 projection (seed 001 eq. 74-90).

Tolerances: exactness (~1e-10) for fields inside the discrete space; the MPI test
compares a 2-rank run with a serial (COMM_SELF) run of the same problem to round-off.
"""

import dolfinx_solver  # noqa: F401

import numpy as np
import pytest
from mpi4py import MPI

import basix.ufl
import dolfinx
from dolfinx import fem, mesh

from coupling.locate import PointsOutsideMesh, owner_ranks
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
