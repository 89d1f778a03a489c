"""Calibration-chamber loading (coupling.apps.penetration.chamber): the vertical stress on
top reaches the base, BC1 replaces the side walls by the forces they carried, and the
coupled chamber carries the increment with its sides on rollers (BC3) or free (BC1)."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.apps.penetration.coupled import CoupledPenetration, DemPenetration, PenetrationParameters

# a chamber 30 grain diameters wide (about 550 disks), 50 kPa on top
CHAMBER = dict(chamber_width=0.09, chamber_depth=0.05, radius=1.5e-3, cone_radius=0.006, kn=5e7,
               velocity=1.0, depth=0.004, dt_factor=3.0, vertical_stress=5e4, consolidation_tol=1e-2,
               window_half_width=0.024, window_depth=0.03, element_size_window=0.005, element_size_far=0.02,
               substeps=50)


def test_vertical_stress_reaches_the_base_and_bc1_keeps_the_lateral_one():
    # consolidated closer to equilibrium than the default, for the balances below
    prm = PenetrationParameters(**(CHAMBER | {"lateral": "stress", "consolidation_tol": 2e-3}))
    model = DemPenetration(prm, log=lambda m: None)
    sim, n = model.sim, model.n_grains
    weight = float(sim.p.mass[:n].sum() * prm.gravity)
    # smooth walls: the base carries the surcharge and the grains' weight
    rows, f = sim.external_force()
    assert f[:, 1].sum() == pytest.approx(-prm.vertical_stress * prm.chamber_width, rel=1e-12)
    assert -sim.walls.force[2, 1] == pytest.approx(prm.vertical_stress * prm.chamber_width + weight, rel=0.02)
    # BC1: the side walls held at the consolidated lateral stress, K0 sigma_v
    targets = [s.target for s in model.servos]
    assert len(targets) == 2 and targets[0] == pytest.approx(targets[1], rel=0.05)
    assert 0.2 < targets[0] / prm.vertical_stress < 1.2
    history = model.run()
    assert np.isfinite([h["q_c"] for h in history]).all()
    # the cone pushes the sand outward: the servos open the walls (in this chamber, 15 cone
    # widths wide, they lag the push by a few FE steps)
    assert sim.walls.point[0, 0] < -prm.chamber_width / 2 and sim.walls.point[1, 0] > prm.chamber_width / 2
    # (the servos lag the push, so the stress at the end overshoots its target: 1.96x with
    # the half-step dashpot, 2.07x with the second-order one; the bound catches a runaway)
    for servo in model.servos:
        assert servo.stress(sim) < 2.5 * servo.target


def test_coupled_chamber_carries_the_increment():
    bcs = {}
    for lateral in ("rigid", "stress"):
        prm = PenetrationParameters(**CHAMBER, lateral=lateral)
        model = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
        rows, f = model.sim.external_force()
        assert len(rows) > 0 and (f[:, 1] < 0).all()            # only the top row is loaded
        assert (model.kinds[rows] == 0).all()                   # window grains, not ghosts
        history = model.run(steps=4)
        assert len(history) == 4 and np.isfinite([h["q_c"] for h in history]).all()
        assert np.abs(model.problem.w.x.array).max() < prm.depth
        bcs[lateral] = len(model.problem.bcs)
    # BC3: the two rollers more than BC1 (the base is clamped in both)
    assert bcs["rigid"] == bcs["stress"] + 2


# the 3D chamber: Hertz spheres of 1.5 mm, a cone of 4 grain radii, 50 kPa under a top plate
CHAMBER_3D = dict(dim=3, chamber_width=0.075, chamber_depth=0.045, radius=1.5e-3, cone_radius=0.006, velocity=1.0,
                  depth=0.004, vertical_stress=5e4, consolidation_tol=1e-2, window_half_width=0.0135,
                  window_depth=0.025, element_size_window=0.005, element_size_far=0.02, substeps=50)


def test_3d_chamber_plate_holds_the_vertical_stress_and_the_cone_passes_it():
    """3D: the top plate, servo-controlled, holds sigma_v over the chamber's square top while
    consolidating and pushing; the base carries it with the grains' weight; the cone's
    spheres pass through the plate (they meet only grains)."""
    prm = PenetrationParameters(**(CHAMBER_3D | {"chamber_depth": 0.02}))
    model = DemPenetration(prm, log=lambda m: None)
    sim, n = model.sim, model.n_grains
    (servo,) = model.servos
    assert servo.area == pytest.approx(prm.chamber_width**2) and servo.target == prm.vertical_stress
    assert servo.stress(sim) == pytest.approx(prm.vertical_stress, rel=1e-2)
    weight = float(sim.p.mass[:n].sum() * prm.gravity)
    assert -sim.walls.force[4, 2] == pytest.approx(prm.vertical_stress * prm.chamber_width**2 + weight, rel=0.03)
    assert len(sim.external_force()[0]) == 0          # no constant forces on top spheres in 3D
    history = model.run()
    q = np.array([h["q_c"] for h in history])
    assert np.isfinite(q).all() and q[-1] > 0.5 * prm.vertical_stress
    # the plate held its stress through the push (a block's lag aside)
    assert servo.stress(sim) == pytest.approx(prm.vertical_stress, rel=0.1)
    # no cone sphere touches the plate: its force is the grains' alone
    wall = sim.walls
    assert not (wall.free_only[sim.nl.ww] & (sim.p.kind[sim.nl.wi] != 0)).any()


def test_3d_coupled_chamber_carries_the_increment_on_rollers(tmp_path):
    prm = PenetrationParameters(**CHAMBER_3D)
    comm = MPI.COMM_WORLD
    model = CoupledPenetration(prm, comm, log=lambda m: None)
    (servo,) = model.servos
    # the plate rests on the window's free grains after the band is held: it keeps their share
    assert servo.stress(model.sim) == pytest.approx(prm.vertical_stress, rel=1e-6)
    assert servo.area < (2 * (prm.window_half_width + prm.ghost_width * 2 * prm.radius)) ** 2
    model.run(steps=1)
    model.save_checkpoint(tmp_path / "ck")
    history = model.run(steps=2)
    assert len(history) == 3 and np.isfinite([h["q_c"] for h in history]).all()
    # a restart continues with the plate's servo (its area from the checkpoint) to the bit
    again = CoupledPenetration(prm, comm, log=lambda m: None, checkpoint=tmp_path / "ck")
    assert again.servos[0].area == servo.area
    assert [h["q_c"] for h in again.run(steps=2)] == [h["q_c"] for h in history]
    assert np.abs(model.problem.w.x.array).max() < prm.depth
    # BC3 in a box: the sides on rollers (no normal displacement; they slide vertically)
    u = model.problem.w.sub(0).collapse()
    x, w = u.function_space.tabulate_dof_coordinates(), u.x.array.reshape(-1, 3)
    half = prm.chamber_width / 2
    for axis in (0, 1):
        side = np.isclose(np.abs(x[:, axis]), half)
        assert side.any() and np.all(w[side, axis] == 0.0)
    sides = np.isclose(np.abs(x[:, :2]), half).any(axis=1) & (x[:, 2] > x[:, 2].min() + 1e-9)
    assert np.abs(w[sides, 2]).max() > 0
    # the window's stress as the continuum's start: vertical about sigma_v, lateral K0 of it
    s = model._window_stress()
    assert len(s) == 3 and -1.5 * prm.vertical_stress < s[2] < -0.6 * prm.vertical_stress
    assert s[2] < s[0] < 0 and s[2] < s[1] < 0


def test_chamber_loading_is_named():
    with pytest.raises(ValueError, match="reach the chamber's base"):
        CoupledPenetration(PenetrationParameters(**(CHAMBER_3D | {"chamber_depth": 0.03})), MPI.COMM_WORLD,
                           log=lambda m: None)
    with pytest.raises(ValueError, match="lateral = 'stress' \\(BC1\\) needs dim = 2"):
        PenetrationParameters(dim=3, vertical_stress=1e5, lateral="stress")
    with pytest.raises(ValueError, match="lateral must be 'rigid'"):
        PenetrationParameters(lateral="membrane")
    with pytest.raises(ValueError, match="vertical_stress must be >= 0"):
        PenetrationParameters(vertical_stress=-1.0)


def test_plastic_continuum_starts_from_the_window_stress_and_restarts(tmp_path):
    """The Drucker-Prager continuum takes the consolidated window's mean stress as its initial
    stress (compressive, vertical about the surcharge), pushes on, and a restart from a
    checkpoint continues with the same plastic state."""
    prm = PenetrationParameters(**CHAMBER, continuum="micropolar_drucker_prager", continuum_friction_deg=35.0)
    comm = MPI.COMM_WORLD
    model = CoupledPenetration(prm, comm, log=lambda m: None)
    sxx, syy = model.initial_stress
    assert -1.6 * prm.vertical_stress < syy < -0.6 * prm.vertical_stress
    assert syy < sxx < 0
    model.run(steps=2)
    # a Jacobian rebuilt at every Newton iteration (a lagged one converged linearly, 50+)
    assert model.stepper._snes.solver.getIterationNumber() <= 6
    model.save_checkpoint(tmp_path / "ck")
    ref = model.run(steps=2)
    again = CoupledPenetration(prm, comm, log=lambda m: None, checkpoint=tmp_path / "ck")
    assert again.initial_stress == model.initial_stress
    got = again.run(steps=2)
    assert [h["q_c"] for h in got] == [h["q_c"] for h in ref]
    for name, f in model.problem.state.committed.items():
        np.testing.assert_array_equal(f.x.array, again.problem.state.committed[name].x.array, err_msg=name)


def test_explicit_plastic_continuum_follows_the_implicit_one_and_restarts(tmp_path):
    """The Drucker-Prager far field stepped explicitly (granfe.explicit, substepped below its
    stability limit) reads the implicit run's q_c within 1 % over the first 12 FE steps (the
    cone in the grains from the 7th; later the two runs part like two packings: a difference
    grows about tenfold an FE step through the grains), and a restart from a checkpoint
    continues it to the bit, plastic state included."""
    runs = {}
    for integrator in ("implicit", "explicit"):
        prm = PenetrationParameters(**CHAMBER, continuum="micropolar_drucker_prager", continuum_friction_deg=35.0,
                                    continuum_integrator=integrator)
        model = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
        runs[integrator] = model, model.run(steps=12)
    model, explicit = runs["explicit"]
    assert model.stepper.substeps >= 1
    q_exp, q_imp = (np.array([h["q_c"] for h in runs[k][1]]) for k in ("explicit", "implicit"))
    assert q_exp[-1] > 0.5 * prm.vertical_stress and model.problem.state.owned("yielding").max() == 1
    assert np.abs(q_exp - q_imp).max() <= 0.01 * np.abs(q_imp).max(), (q_exp, q_imp)
    model.save_checkpoint(tmp_path / "ck")
    ref = model.run(steps=2)
    again = CoupledPenetration(model.prm, MPI.COMM_WORLD, log=lambda m: None, checkpoint=tmp_path / "ck")
    assert [h["q_c"] for h in again.run(steps=2)] == [h["q_c"] for h in ref]
    for name, f in model.problem.state.committed.items():
        np.testing.assert_array_equal(f.x.array, again.problem.state.committed[name].x.array, err_msg=name)


@pytest.mark.mpi
def test_plastic_chamber_on_any_rank_count():
    """The plastic chamber runs on every rank count with one initial stress and one q_c on
    all ranks (the grains are replicated; the continuum's solve is redundant)."""
    comm = MPI.COMM_WORLD
    prm = PenetrationParameters(**CHAMBER, continuum="micropolar_drucker_prager", continuum_friction_deg=35.0,
                                lateral="stress")
    model = CoupledPenetration(prm, comm, log=lambda m: None)
    history = model.run(steps=3)
    q = [h["q_c"] for h in history]
    assert np.isfinite(q).all()
    assert all(other == q for other in comm.allgather(q))
    assert all(s == model.initial_stress for s in comm.allgather(model.initial_stress))


def test_calibrated_continuum_takes_the_cell_tests_constants_and_angles():
    """continuum_constants = "calibrated": the continuum's constants are those of element tests
    on a periodic cell of the grains at the window's mean stress (softer in shear than the
    lattice estimate: contacts slide and open), and the plastic continuum takes the cell's
    peak friction and dilatancy angles instead of the scene's."""
    prm = PenetrationParameters(**CHAMBER, continuum="micropolar_drucker_prager",
                                continuum_constants="calibrated", continuum_friction_deg=20.0,
                                continuum_hardening=2e6)
    model = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
    cal, m = model.contact_stats["calibration"], model.material_fe
    assert cal["pressure"] == pytest.approx(-0.5 * sum(model.initial_stress), rel=1e-12)
    assert m.mu + m.kappa / 2 == pytest.approx(cal["shear_modulus"], rel=1e-9)
    est = cal["lattice_estimate"]
    assert cal["shear_modulus"] < est["mu"] + est["kappa"] / 2
    dp = model.problem.model.material
    assert dp.friction_deg == pytest.approx(cal["friction_peak_deg"]) and dp.friction_deg != 20.0
    assert 0 <= dp.dilatancy_deg <= dp.friction_deg
    assert dp.hardening == 2e6
    history = model.run(steps=2)
    assert np.isfinite([h["q_c"] for h in history]).all()


def test_continuum_integrator_is_named():
    with pytest.raises(ValueError, match="continuum_integrator"):
        PenetrationParameters(continuum_integrator="verlet")
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="continuum_damping must be >= 0"):
            PenetrationParameters(continuum_integrator="explicit", continuum_damping=bad)
    with pytest.raises(ValueError, match="continuum_damping .* the explicit continuum's"):
        PenetrationParameters(continuum_damping=100.0)
    assert PenetrationParameters(continuum_integrator="explicit", continuum_damping=100.0).continuum_damping == 100.0


def test_continuum_choices_are_named():
    with pytest.raises(ValueError, match="continuum_constants must be 'lattice', 'calibrated', "
                                         "'window' or 'window_isotropic'"):
        PenetrationParameters(continuum_constants="measured")
    with pytest.raises(ValueError, match="'micropolar_drucker_prager' needs vertical_stress > 0"):
        PenetrationParameters(dim=3, continuum="micropolar_drucker_prager")


def test_hardening_is_validated():
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="continuum_hardening must be >= 0 Pa"):
            PenetrationParameters(continuum_hardening=bad)


def test_force_exchange_lets_the_continuum_compliance_reach_the_window(tmp_path):
    """interface = 'forces' (coupling.reactions): the ghosts' reactions load the continuum and
    nothing of it is prescribed, so the window's edge yields as much as the continuum lets
    it: twice as stiff, half the ghosts' displacement (the overlapping exchange moves them
    by displacements alone, nearly whatever the stiffness). A restart continues to the bit."""
    comm = MPI.COMM_WORLD
    base = CHAMBER | {"substeps": 10, "relaxation": 0.3, "depth": 0.002}
    moved = {}
    for interface in ("loose", "forces"):
        for stiffness in (1.0, 2.0):
            prm = PenetrationParameters(**base, interface=interface, continuum_stiffness=stiffness)
            model = CoupledPenetration(prm, comm, log=lambda m: None)
            n_bcs = moved.setdefault("bcs", len(model.problem.bcs))
            if interface == "forces" and stiffness == 1.0:
                assert len(model.problem.bcs) == n_bcs - 1   # the window's prescribed nodes gone
                model.run(steps=40)
                model.save_checkpoint(tmp_path / "ck")
            history = model.run()
            assert np.isfinite([h["q_c"] for h in history]).all() and history[-1]["q_c"] > 0
            u = model._ghost_motion()[0]
            moved[interface, stiffness] = float(np.sqrt(np.mean(u**2)))
            if interface == "forces" and stiffness == 1.0:
                again = CoupledPenetration(prm, comm, log=lambda m: None, checkpoint=tmp_path / "ck")
                assert [h["q_c"] for h in again.run()] == [h["q_c"] for h in history]
    assert moved["forces", 2.0] / moved["forces", 1.0] == pytest.approx(0.5, abs=0.05)
    assert moved["loose", 2.0] / moved["loose", 1.0] > 0.75


def test_force_exchange_is_named():
    with pytest.raises(ValueError, match="'forces'"):
        PenetrationParameters(interface="force")
    with pytest.raises(ValueError, match="consolidated state"):
        PenetrationParameters(dim=3, interface="forces")


PROBED_3D = CHAMBER_3D | {"substeps": 10, "relaxation": 0.3, "interface": "forces"}


@pytest.fixture(scope="module")
def affine_3d():
    """The 3D forces chamber with the affine (Voigt) constants, unprobed."""
    return CoupledPenetration(PenetrationParameters(**PROBED_3D), MPI.COMM_WORLD, log=lambda m: None)


def test_window_constants_probe_the_windows_modulus_in_situ(affine_3d):
    """continuum_constants = 'window': the affine (Voigt) constants scaled to the consolidated
    window's constrained modulus, probed by a tenth more stress on its plate; the probe puts
    the grains and the plate back (the same packing to the bit as without it)."""
    comm, affine = MPI.COMM_WORLD, affine_3d
    model = CoupledPenetration(PenetrationParameters(**PROBED_3D, continuum_constants="window"), comm,
                               log=lambda m: None)
    probe = model.contact_stats["window_modulus"]
    assert probe["strain"] < 0 and probe["stress_change"] < 0
    assert probe["modulus"] == pytest.approx(probe["stress_change"] / probe["strain"])
    # the grains relax where the affine estimate moves them with the mean strain: softer
    assert 0.2 < probe["voigt_scale"] < 1.0
    assert np.array_equal(model.sim.p.x, affine.sim.p.x)
    assert np.array_equal(model.sim.walls.point, affine.sim.walls.point)
    scale = probe["voigt_scale"]
    for name in ("lam", "mu", "kappa", "gamma"):
        assert getattr(model.material_fe, name) == pytest.approx(scale * getattr(affine.material_fe, name))
    history = model.run(steps=3)
    assert np.isfinite([h["q_c"] for h in history]).all()
    with pytest.raises(ValueError, match="3D chamber's top"):
        PenetrationParameters(continuum_constants="window")


def test_window_isotropic_constants_take_the_lateral_stress_too(affine_3d):
    """continuum_constants = 'window_isotropic': lam and the shear modulus both from the
    probe (the band held: the window's sides barely strain, so lam is the lateral stress the
    probe raised over its vertical strain and 2 G + lam its constrained modulus); mu, kappa
    and the length keep the affine ratios. The grains' lateral stress follows the vertical
    one far more than the affine Poisson ratio (~0.04) says."""
    model = CoupledPenetration(PenetrationParameters(**PROBED_3D, continuum_constants="window_isotropic"),
                               MPI.COMM_WORLD, log=lambda m: None)
    probe, m, a = model.contact_stats["window_modulus"], model.material_fe, affine_3d.material_fe
    # the band held, the sides barely strain; the fitted isotropic law gives back the
    # stress changes the probe raised, vertical and lateral
    ez, eh = probe["strain"], probe["lateral_strain"]
    assert abs(eh) < 0.2 * abs(ez)
    lam, g = probe["lam"], probe["shear_modulus"]
    assert lam * (ez + 2 * eh) + 2 * g * ez == pytest.approx(probe["stress_change"], rel=0.02)
    assert lam * (ez + 2 * eh) + 2 * g * eh == pytest.approx(probe["lateral_stress_change"], rel=0.02)
    assert 0.2 < probe["lateral_ratio"] < 1.0
    assert probe["lateral_ratio"] > 3 * a.lam / (a.lam + 2 * a.mu + a.kappa)
    assert m.lam == probe["lam"]
    assert 2 * m.mu + m.kappa == pytest.approx(2 * probe["shear_modulus"], rel=1e-12)
    for name in ("mu", "kappa", "gamma"):
        assert getattr(m, name) == pytest.approx(probe["voigt_scale"] * getattr(a, name), rel=1e-12)
    assert np.array_equal(model.sim.p.x, affine_3d.sim.p.x)
