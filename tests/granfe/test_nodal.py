"""Nodal loads and the partition weight: the loads a partitioned coupling hands the continuum
(``N^T f`` of particle reactions) and the weight that takes the material out where grains
carry it."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from dolfinx.fem.petsc import assemble_vector

from granfe.dynamics import GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

MAT = MicropolarMaterial.from_engineering(1.0e8, 0.3, length=0.02, kappa_over_mu=0.5, rho=2000.0)


def cantilever(prefix, degree=(1, 1)):
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [12, 3])
    problem = MicropolarProblem(domain, MAT, prefix=prefix, degree=degree)
    clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
    problem.fix(clamp, "u")
    problem.fix(clamp, "phi")
    return problem


def traction_vector(problem, t):
    """The assembled external work vector of a traction t on the right end (V's local layout)."""
    right = problem.facets(lambda x: np.isclose(x[0], 1.0))
    tags = mesh.meshtags(problem.domain, 1, np.sort(right).astype(np.int32), np.ones(len(right), np.int32))
    ds = ufl.Measure("ds", domain=problem.domain, subdomain_data=tags)
    dw = ufl.split(ufl.TestFunction(problem.V))
    b = assemble_vector(fem.form(ufl.inner(fem.Constant(problem.domain, np.array(t)), dw[0]) * ds(1)))
    b.ghostUpdate(addv=1, mode=1)   # ADD, REVERSE
    out = fem.Function(problem.V)
    out.x.petsc_vec.array[:] = b.array_r
    out.x.scatter_forward()
    b.destroy()
    return out.x.array.copy()


@pytest.mark.mpi
def test_nodal_load_equals_the_traction_it_lumps():
    """Nodal forces set to a traction's assembled vector give that traction's solution (the
    vertex rule carries the vector exactly), statically and through the affine dynamic step."""
    t = (2e4, -5e4)
    ref = cantilever("nodal_ref_")
    ref.traction(lambda x: np.isclose(x[0], 1.0), t)
    ref.solve()
    prob = cantilever("nodal_")
    load = prob.nodal_load("u")
    load.set(traction_vector(prob, t))
    prob.solve()
    scale = np.abs(ref.w.x.array).max()
    assert scale > 1e-6
    assert np.abs(prob.w.x.array - ref.w.x.array).max() < 1e-10 * scale
    assert np.allclose(load.values(), traction_vector(prob, t) * (load.values() != 0))

    runs = []
    for nodal in (False, True):
        p = cantilever(f"nodal_dyn{int(nodal)}_")
        if nodal:
            ld = p.nodal_load("u")
        else:
            ld = p.traction(lambda x: np.isclose(x[0], 1.0), fem.Constant(p.domain, np.zeros(2)))
        st = GeneralizedAlpha(p, 2e-5, rho_inf=0.8, prefix=f"nodal_dyn_st{int(nodal)}_")
        assert st._affine is not None
        for k in range(10):
            tk = np.array(t) * np.sin(0.2 * (k + 1))
            if nodal:
                ld.set(traction_vector(p, tk))
            else:
                ld.value = tk
            st.step()
        runs.append(p.w.x.array.copy())
    assert np.abs(runs[0]).max() > 0
    assert np.abs(runs[1] - runs[0]).max() < 1e-10 * np.abs(runs[0]).max()


@pytest.mark.mpi
def test_partition_weight_scales_the_material():
    """A uniform weight c divides a loaded cantilever's displacement by c; a weight that
    vanishes (1e-6) beyond x = 0.5 leaves the clamped half carrying the load alone: the
    free half then moves rigidly (no strain energy of its own)."""
    t = (0.0, -1e4)
    ref = cantilever("weight_ref_")
    ref.traction(lambda x: np.isclose(x[0], 1.0), t)
    ref.solve()
    double = cantilever("weight_two_")
    double.set_weight(fem.Constant(double.domain, 2.0))
    double.traction(lambda x: np.isclose(x[0], 1.0), t)
    double.solve()
    assert np.allclose(double.w.x.array, 0.5 * ref.w.x.array, rtol=1e-10, atol=1e-14)

    # a weight that vanishes beyond x = 0.5, loaded at x = 0.5: the clamped half carries the
    # load as a cantilever half as long would (the weightless half adds 1e-6 of its stiffness)
    dg0 = fem.functionspace(ref.domain, ("DG", 0))
    weight = fem.Function(dg0)
    weight.interpolate(lambda x: np.where(x[0] < 0.5, 1.0, 1e-6))
    runs = []
    for length, cells in ((1.0, 12), (0.5, 6)):
        domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [length, 0.2]], [cells, 3])
        p = MicropolarProblem(domain, MAT, prefix=f"weight_half{cells}_", degree=(1, 1))
        clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
        p.fix(clamp, "u")
        p.fix(clamp, "phi")
        if length == 1.0:
            w = fem.Function(fem.functionspace(domain, ("DG", 0)))
            w.interpolate(lambda x: np.where(x[0] < 0.5, 1.0, 1e-6))
            p.set_weight(w)
        load = p.nodal_load("u")
        Vu, u_dofs = p.V.sub(0).collapse()
        xy = Vu.tabulate_dof_coordinates()
        F = np.zeros_like(p.w.x.array)
        F[np.asarray(u_dofs).reshape(-1, 2)[np.isclose(xy[:, 0], 0.5), 1]] = -1e3
        load.set(F)
        p.solve()
        n = Vu.dofmap.index_map.size_local   # owned nodes, gathered from every rank
        u = p.w.sub(0).collapse().x.array.reshape(-1, 2)[:n]
        xy = np.concatenate(MPI.COMM_WORLD.allgather(xy[:n]))
        u = np.concatenate(MPI.COMM_WORLD.allgather(u))
        keep = xy[:, 0] <= 0.5 + 1e-12
        xr = np.round(xy[keep], 9)   # one order in both meshes, whatever the partition
        order = np.lexsort((xr[:, 1], xr[:, 0]))
        runs.append(u[keep][order])
    full, short = runs
    assert np.abs(short).max() > 0
    assert np.abs(full - short).max() < 1e-4 * np.abs(short).max()


def test_nodal_load_refuses_what_it_cannot_carry():
    prob = cantilever("nodal_bad_", degree=(2, 1))
    with pytest.raises(ValueError, match="degree-1"):
        prob.nodal_load("u")
    with pytest.raises(ValueError, match="no field .chi."):
        prob.nodal_load("chi")
    ok = cantilever("nodal_bad1_")
    load = ok.nodal_load("u")
    with pytest.raises(ValueError, match="local size"):
        load.set(np.zeros(3))
    F = np.zeros_like(ok.w.x.array)
    F[load.dofs[0]] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        load.set(F)
