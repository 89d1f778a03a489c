"""3D coupled penetration: geostatic continuum state against its closed form, restart equal to
the uninterrupted run, the cone meeting the grains; serial and under mpiexec -n 2."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.apps.penetration.coupled import CoupledPenetration, PenetrationParameters

# a few hundred spheres, a coarse mesh: the scene of scenes/cpt_3d.toml at toy size
TINY = dict(dim=3, chamber_width=0.14, chamber_depth=0.08, window_half_width=0.02, window_depth=0.04,
            ghost_width=1.5, handshake=1.0, radius=3.5e-3, cone_radius=0.008, depth=0.008,
            velocity=0.8, element_size_window=0.01, element_size_far=0.05, settle_time=0.04,
            substeps=20)


@pytest.fixture(scope="module")
def cone(tmp_path_factory):
    comm = MPI.COMM_WORLD
    prm = PenetrationParameters(**TINY)
    cpt = CoupledPenetration(prm, comm, log=lambda m: None)
    w_geo = cpt.problem.w.x.array.copy()
    where = comm.bcast(str(tmp_path_factory.mktemp("ckpt")) if comm.rank == 0 else None, root=0)
    cpt.run(steps=4)
    cpt.save_checkpoint(where)
    cpt.run()
    return prm, cpt, w_geo, where


@pytest.mark.mpi
def test_geostatic_state_is_uniaxial_compression(cone):
    """Gravity plus the K0 side traction: u = (0, 0, u_z(z)) with
    u_z = -(rho g / M) [s (z - z_b) - (z^2 - z_b^2) / 2], M = lam + 2 mu + kappa."""
    prm, cpt, w_geo, _ = cone
    V = cpt.problem.V
    Vu, parent = V.sub(0).collapse()
    x = Vu.tabulate_dof_coordinates()
    n_owned = Vu.dofmap.index_map.size_local
    u = w_geo[np.asarray(parent)].reshape(-1, 3)[:n_owned]
    z, s, zb = x[:n_owned, 2], cpt.surface, cpt.surface - prm.chamber_depth
    m = cpt.material_fe
    exact = -(m.rho * prm.gravity / (m.lam + 2 * m.mu + m.kappa)) * (s * (z - zb) - (z**2 - zb**2) / 2)
    comm = cpt.comm
    scale = comm.allreduce(np.abs(exact).max(initial=0.0), MPI.MAX)
    lateral = comm.allreduce(np.abs(u[:, :2]).max(initial=0.0), MPI.MAX)
    error = comm.allreduce(np.abs(u[:, 2] - exact).max(initial=0.0), MPI.MAX)
    assert scale > 0
    # physics tolerance: u_z is quadratic in z and the tetrahedra are linear; on this coarse
    # mesh the nodal error is 1 % (lateral) and 2 % (u_z) and halves as h halves (measured:
    # 0.4 % and 0.6 % at h / 4).
    assert lateral < 0.03 * scale
    assert error < 0.05 * scale


@pytest.mark.mpi
def test_restart_reproduces_the_run(cone):
    """run(4) + checkpoint + run(rest) equals a fresh object restarted from the checkpoint."""
    prm, cpt, _, where = cone
    again = CoupledPenetration(prm, cpt.comm, log=lambda m: None, checkpoint=where)
    assert len(again.history) == 4 and again.depth < cpt.depth
    again.run()
    keys = ("q_c", "f_s", "depth", "interface_mismatch")
    a = np.array([[h[k] for k in keys] for h in cpt.history])
    b = np.array([[h[k] for k in keys] for h in again.history])
    assert a.shape == b.shape == (cpt.n_steps, 4)
    assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(a).max())
    assert np.allclose(again.sim.p.x, cpt.sim.p.x, rtol=0, atol=1e-15)
    assert np.allclose(again.problem.w.x.array, cpt.problem.w.x.array, rtol=0,
                       atol=1e-12 * np.abs(cpt.problem.w.x.array).max())


@pytest.mark.mpi
def test_cone_meets_the_grains(cone):
    prm, cpt, _, _ = cone
    qc = np.array([h["q_c"] for h in cpt.history])
    assert np.all(np.isfinite(qc))
    assert qc[-1] > 0 and qc.max() > 1e3          # the grains push back once the tip is in
    assert cpt.contact_stats["coordination"] > 3.0   # a settled, load-bearing packing
    assert 0.5 < cpt.contact_stats["solid_fraction"] < 0.74


def test_pile_needs_3d():
    with pytest.raises(ValueError, match="shape = 'pile' needs dim = 3"):
        PenetrationParameters(shape="pile")


# the reduced 2D scene of benchmarks/stability.py
SMALL_2D = dict(settle_time=0.08, depth=0.008, chamber_width=0.2, chamber_depth=0.12, radius=2e-3,
                element_size_far=0.03)


def test_too_fast_a_push_stops_with_its_last_state(tmp_path):
    """A cone moving more than 0.05 grain radius per DEM step is refused by name, and the
    settled state is kept (benchmarks/stability.py maps where that happens)."""
    from coupling.apps.penetration.run import run_penetration

    comm = MPI.COMM_WORLD
    out = comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0)
    prm = PenetrationParameters(**SMALL_2D, velocity=10.0)
    with pytest.raises(RuntimeError, match=r"velocity = 10.0 m/s moves the penetrator .* per DEM step"):
        run_penetration(prm, out, comm, frames=1, fields=False, particles=False, png=False,
                        progress=False, log=lambda m: None)
    assert (tmp_path / "last_good" / "grains.npz").exists()


def test_time_step_past_critical_is_refused():
    with pytest.raises(ValueError, match=r"dt_factor = 40.0 puts the DEM step above the critical"):
        PenetrationParameters(**SMALL_2D, dt_factor=40.0)
    PenetrationParameters(**SMALL_2D, dt_factor=20.0)  # at the linear law's limit


def test_failed_set_up_keeps_the_settled_grains(tmp_path):
    """Too short a settle leaves no load-bearing packing: the set-up stops naming the key,
    and the grains computed so far are written."""
    from coupling.apps.penetration.run import run_penetration

    comm = MPI.COMM_WORLD
    out = comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0)
    prm = PenetrationParameters(**(TINY | {"settle_time": 1e-4}))
    with pytest.raises(RuntimeError, match=r"set-up failed: settle_time = 0.0001 s leaves a coordination"):
        run_penetration(prm, out, comm, frames=1, fields=False, particles=False, png=False,
                        progress=False, log=lambda m: None)
    if comm.rank == 0:
        saved = np.load(tmp_path / "last_good" / "grains.npz")
        assert np.isfinite(saved["x"]).all() and len(saved["x"]) > 100


def test_continuum_stiffness_scales_the_derived_constants():
    comm = MPI.COMM_WORLD
    a = CoupledPenetration(PenetrationParameters(**SMALL_2D), comm, log=lambda m: None).material_fe
    b = CoupledPenetration(PenetrationParameters(**SMALL_2D, continuum_stiffness=10.0), comm,
                           log=lambda m: None).material_fe
    for name in ("lam", "mu", "kappa", "alpha", "beta", "gamma"):
        assert getattr(b, name) == pytest.approx(10.0 * getattr(a, name), rel=1e-12)
    assert b.rho == a.rho
    with pytest.raises(ValueError, match="continuum_stiffness must be > 0"):
        PenetrationParameters(**SMALL_2D, continuum_stiffness=0.0)
