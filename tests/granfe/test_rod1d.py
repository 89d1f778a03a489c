"""1D micropolar Timoshenko rod (seed 001 §2.2): closed forms, convergence, serial == 2 ranks."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D, cantilever_tip

L, R = 0.2, 0.005
A, I = np.pi * R**2, np.pi * R**4 / 4
F = (1e3, 1e3, 0.0)
MAT = MicropolarMaterial.from_engineering(10e9, 0.3, length=0.01, kappa_over_mu=0.1,
                                          gamma_over_l2mu=0.05)


def _tip(n, formulation="seed", comm=MPI.COMM_SELF):
    rod = Rod1D(MAT, L, A, I, n, comm, formulation=formulation)
    return rod.solve(F, clamp="right").at(0.0, comm)


@pytest.mark.parametrize("n", [2, 5, 10, 20])
def test_axial_tip_is_exact(n):
    u_exact = F[0] * L / ((MAT.lam + 2 * MAT.mu + MAT.kappa) * A)
    assert _tip(n)[0] == pytest.approx(u_exact, rel=1e-12)


@pytest.mark.parametrize("formulation", ["seed", "energy"])
def test_transverse_tip_converges_to_closed_form(formulation):
    v_exact = cantilever_tip(MAT, L, A, I, F[:2], formulation)[1]
    ns = np.array([2, 4, 8, 16])
    err = np.array([v_exact - _tip(n, formulation)[1] for n in ns])
    assert np.all(err > 0) and np.all(np.diff(err) < 0)  # monotone from below
    rates = np.log(err[:-1] / err[1:]) / np.log(2)
    assert rates.min() > 1.9  # observed ~2 (theta linear)
    assert abs(err[-1]) / v_exact < 1e-3


def test_seed_fig4_magnitudes():
    # seed Fig. 4: axial ~0.018 cm, transverse ~3 cm at 1 kN; 2 elements visibly coarse
    u, v, _ = _tip(20)
    assert u == pytest.approx(1.84e-4, rel=1e-2)
    assert 0.029 < v < 0.0300
    assert _tip(2)[1] < 0.95 * v


def test_energy_form_is_symmetric_seed_form_is_not():
    Ke = Rod1D(MAT, L, A, I, 3, MPI.COMM_SELF, formulation="energy").K.toarray()
    Ks = Rod1D(MAT, L, A, I, 3, MPI.COMM_SELF, formulation="seed").K.toarray()
    assert np.abs(Ke - Ke.T).max() < 1e-12 * np.abs(Ke).max()
    assert np.abs(Ks - Ks.T).max() > 1e-3 * np.abs(Ks).max()


def test_scaling_scales_rows():
    K1 = Rod1D(MAT, L, A, I, 2, MPI.COMM_SELF).K.toarray()
    rod = Rod1D(MAT, L, A, I, 2, MPI.COMM_SELF, scaling=(2.0, 3.0, 5.0))
    g = np.empty(K1.shape[0])
    for gk, name in zip((2.0, 3.0, 5.0), ("u", "v", "theta"), strict=False):
        g[rod.field_dofs[name][0]] = gk
    assert np.allclose(rod.K.toarray(), g[:, None] * K1, rtol=1e-12, atol=1e-12 * np.abs(K1).max())


@pytest.mark.parametrize("bad", [dict(length=-1.0), dict(n_elements=0), dict(formulation="x"),
                                 dict(scaling=(1.0, 0.0, 1.0))])
def test_bad_input_names_field(bad):
    kw = dict(material=MAT, length=L, area=A, inertia=I, n_elements=2) | bad
    with pytest.raises(ValueError, match=next(iter(bad))):
        Rod1D(**kw)


@pytest.mark.mpi
def test_serial_equals_parallel():
    comm = MPI.COMM_WORLD
    par = _tip(10, comm=comm)
    ser = _tip(10, comm=MPI.COMM_SELF)
    assert comm.allreduce(float(np.abs(par - ser).max()), op=MPI.MAX) < 1e-11 * np.abs(ser).max()
