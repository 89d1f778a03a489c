"""Saturated coupled cone penetration (CPTu, `coupling.apps.penetration.saturated`): the
``[fluid]`` table, a dry scene without fluid, one pressure field across the overlap, the
fluid's mass balance, the sign of the cone's first push, the forces between fluid steps,
and u2 from drained to undrained.

Tolerances: exactness (1e-8 of the stored-fluid rate) for the mass balance through the
drained surface (the weak form tested with q = 1: nothing but round-off and the direct
solve); the interval's forces against the next fluid step to first order in the grains'
displacement (1e-5); the rest are signs and orderings of physics (a contractive window
pushed drained and undrained), each measured with a margin (u2 9.2 kPa at V = 154 against
34 Pa at V = 0.015); serial == 2 ranks to 1e-8 (the fluid's step before any grain moves:
pushed, the runs part as chaotic packings do). A fluid step every 10 DEM steps, as a
scene would take it (`fluid.every`). The field, the balance, the cone's first push, the
interval's forces and serial == 2 ranks also in 3D, on a small window of spheres
(``SMALL_3D``, ~30 s to set up and push)."""

from types import SimpleNamespace

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem

from coupling.apps.penetration.coupled import CoupledPenetration
from coupling.apps.penetration.penetrators import tip_height
from coupling.apps.penetration.run import _set_up
from coupling.apps.penetration.saturated import ChamberFlow, SaturatedPenetration, bulk_modulus, constrained_modulus
from coupling.scene import SceneError, load_scene
from dem.state import FREE
from granfe.probe import probe

# a small loose (contractive) window: jitter 0.4 and friction 0.8 leave a porosity ~0.45
SMALL = {"scene": {"name": "cptu_test", "kind": "penetration", "dimension": 2},
         "chamber": {"width": 0.16, "depth": 0.12, "element_size_window": 0.008,
                     "element_size_far": 0.03},
         "grains": {"radius": 1.5e-3, "jitter": 0.4, "friction": 0.8, "settle_time": 0.15},
         "window": {"half_width": 0.025, "depth": 0.045, "handshake": 1.0},
         "penetrator": {"radius": 0.0045, "velocity": 0.2, "depth": 0.012},
         "coupling": {"substeps": 50, "dt_factor": 4.0},
         "output": {"checkpoint_every": 0}}
# the same in 3D: ~1500 spheres (E of quartz / 1000) round a cone of 2.5 grain radii
SMALL_3D = {"scene": {"name": "cptu_test_3d", "kind": "penetration", "dimension": 3},
            "chamber": {"width": 0.1, "depth": 0.07, "element_size_window": 0.008, "element_size_far": 0.03},
            "grains": {"radius": 2.0e-3, "jitter": 0.3, "friction": 0.8, "youngs_modulus": 2.9e7,
                       "settle_time": 0.05},
            "window": {"half_width": 0.016, "depth": 0.03, "handshake": 1.0, "ghost_width": 2.0},
            "penetrator": {"radius": 0.005, "velocity": 0.2, "depth": 0.006},
            "coupling": {"substeps": 50},
            "output": {"checkpoint_every": 0}}
FLUID = {"enabled": True, "permeability": 1e-11, "compressibility": 1e-6,
         "saturation_time": 0.02, "every": 10}


def scene(fluid=None, dim=2, **sections):
    data = {k: dict(v) for k, v in (SMALL if dim == 2 else SMALL_3D).items()}
    for name, values in sections.items():
        data.setdefault(name, {}).update(values)
    if fluid is not None:   # (3D: the dry continuum, the Biot one is 2D so far)
        data["fluid"] = {**FLUID, **({"continuum": "drained"} if dim == 3 else {}), **fluid}
    return load_scene(None, data)


def quiet(message):
    pass


@pytest.mark.parametrize("bad, named", [({"permeability": -1e-12}, "fluid.permeability must be > 0"),
                                        ({"permeability": 0.0}, "fluid.permeability must be > 0"),
                                        ({"viscosity": -1e-3}, "fluid.viscosity must be > 0"),
                                        ({"density": -1.0}, "fluid.density must be >= 0"),
                                        ({"compressibility": -1e-9}, "fluid.compressibility must be >= 0"),
                                        ({"saturation_time": -0.1}, "fluid.saturation_time must be >= 0"),
                                        ({"permeability": "high"}, "fluid.permeability"),
                                        ({"every": 0}, "fluid.every must be an integer >= 1"),
                                        ({"every": 7}, "fluid.every = 7 DEM steps must divide coupling.substeps"),
                                        ({"response_every": 0}, "fluid.response_every must be an integer >= 1"),
                                        ({"response_every": 3},
                                         "fluid.response_every = 3 must divide fluid.every = 10"),
                                        ({"continuum": "undrained"},
                                         "fluid.continuum must be one of 'biot', 'drained'")])
def test_fluid_table_names_the_bad_key(bad, named):
    with pytest.raises(SceneError, match=named.replace(".", r"\.")):
        scene(bad)


def test_fluid_needs_a_loose_run_in_a_fixed_window():
    with pytest.raises(SceneError, match="fluid.enabled = true needs coupling.interface = 'loose'"):
        scene({}, coupling={"interface": "iqn-ils"})
    assert scene({}, output={"checkpoint_every": 5}).output.checkpoint_every == 5
    with pytest.raises(SceneError, match="unknown key fluid.permeabilty"):
        scene({"permeabilty": 1e-11})
    assert scene({}).fluid_parameters().permeability == FLUID["permeability"]
    assert scene({"enabled": False}).fluid_parameters() is None
    assert scene({}, dim=3).fluid_parameters().permeability == FLUID["permeability"]   # (3D too)
    with pytest.raises(SceneError, match="fluid.continuum = 'biot' is 2D so far"):
        scene({"continuum": "biot"}, dim=3)


def test_the_moduli_of_the_fluids_storage():
    """The continuum's bulk modulus in its storage: lam + G in plane strain, lam + 2 G / 3 in
    3D (G = mu + kappa / 2); the constrained modulus lam + 2 G in both."""
    m = SimpleNamespace(lam=3.0e6, mu=2.0e6, kappa=1.0e6)
    G = m.mu + m.kappa / 2
    assert bulk_modulus(m, 2) == pytest.approx(m.lam + G, rel=1e-15)
    assert bulk_modulus(m, 3) == pytest.approx(m.lam + 2 * G / 3, rel=1e-15)
    assert constrained_modulus(m) - bulk_modulus(m, 3) == pytest.approx(4 * G / 3, rel=1e-15)


def test_a_scene_without_fluid_builds_none():
    s = scene()
    assert s.fluid_parameters() is None
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    assert type(cpt) is CoupledPenetration and not hasattr(cpt, "flow")
    record = cpt.advance()
    assert "u2" not in record and "q_t" not in record


def run(velocity, dim=2, **fluid):
    """The small scene saturated, pushed at ``velocity`` [m/s]; also the pressure the cone's
    first step raises in the saturated window at rest (:func:`cone_only`)."""
    s = scene(fluid, dim, penetrator={"velocity": velocity})
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    assert isinstance(cpt, SaturatedPenetration)
    first = cone_only(cpt)
    cpt.run()
    return cpt, first


def cone_only(cpt):
    """A fluid step with the grains held where they are (their displacement rate 0: two
    solves at one state) and the continuum at rest: the cone's intrusion the only source.
    Returns the readings; the state is put back."""
    flow, dt = cpt.flow, cpt.fluid.every * cpt.sim.dt
    saved = flow.p.x.array.copy()
    flow.solve(dt)
    flow.p.x.array[:] = 0.0
    flow.step(dt)
    out = flow.readings()
    out["p_min"] = cpt.comm.allreduce(float(flow.p.x.array.min()), op=MPI.MIN)
    tip = flow.cone_tip()
    out["below_tip"] = float(probe(flow.p, tip - cpt.prm.radius * np.eye(3)[flow.ax])[0, 0])
    flow.p.x.array[:] = saved
    return out


@pytest.fixture(scope="module")
def fast():
    return run(0.2)


@pytest.fixture(scope="module")
def fast_3d():
    return run(0.2, dim=3, permeability=1e-10)   # (V ~ 0.1)


@pytest.fixture(params=[2, 3], ids=["2d", "3d"])
def pushed(request):
    """The small scene's push, 2D and 3D."""
    return request.getfixturevalue("fast" if request.param == 2 else "fast_3d")


def test_the_penetrators_body_is_solid_to_the_fluid():
    """The points carrying the penetrator's solid into the fluid fill its section (2D: a grid
    cell's area each, within 2 % of the cone and shaft's area) or its body (3D: its volume
    over their count, pi R^2 (L + h / 3) exactly), inside its outline."""
    for dim in (2, 3):
        s = scene({}, dim)
        prm = s.parameters()
        flow = SimpleNamespace(cpt=SimpleNamespace(prm=prm), gdim=dim)
        x, each = ChamberFlow._cone_points(flow)
        R, h = prm.cone_radius, tip_height(prm)
        top = h + prm.depth + 2 * R
        ax = dim - 1
        across = np.linalg.norm(x[:, :ax], axis=1)
        assert np.all(across <= R) and np.all(x[:, ax] >= across * h / R) and np.all(x[:, ax] <= top)
        if dim == 2:
            assert len(x) * each == pytest.approx(2 * R * (top - h) + R * h, rel=0.02)
        else:
            assert len(x) * each == pytest.approx(np.pi * R**2 * (top - h + h / 3), rel=1e-12)


def test_the_pressure_is_one_field_across_the_overlap(pushed):
    cpt, _ = pushed
    flow = cpt.flow
    # one continuous P1 field on the continuum's own mesh, over the whole chamber
    assert flow.p.function_space.mesh is cpt.problem.domain
    element = flow.p.function_space.ufl_element()
    assert element.basix_element.discontinuous is False and element.embedded_superdegree == 1
    w = flow.weight.x.array
    assert w.min() == 0.0 and w.max() == 1.0 and np.any((w > 0) & (w < 1))   # the blend
    # the weight is the coupling's: 1 wherever the grains prescribe the continuum's nodes
    X = flow.Vn.tabulate_dof_coordinates()[:, :cpt.prm.dim]
    assert np.all(w[cpt.regions.prescribed_nodes(X)] == 1.0)
    # and 0 beyond the ghost band, where no grain is
    reach = cpt.regions.window.signed_distance(X) > cpt.prm.ghost_width * 2 * cpt.prm.radius
    assert np.all(w[reach] == 0.0)
    # the pressure reaches the continuum across the overlap (not a window-only field)
    p = flow.p.x.array
    comm = cpt.comm
    assert comm.allreduce(float(np.abs(p[w == 0]).max(initial=0.0)), op=MPI.MAX) > 1.0


def test_the_fluid_balances_through_the_drained_surface(pushed):
    """The weak form tested with q = 1: what enters through the drained top is what the
    storage (n beta_f, and (1 - w) / K with a drained continuum) took in the step (no-flux
    elsewhere, and the source's int v . grad 1 = 0)."""
    cpt, _ = pushed
    flow = cpt.flow
    dt = cpt.fluid.every * cpt.sim.dt
    storage = flow.params.compressibility * flow.porosity
    if flow.skeleton_storage is not None:
        storage = storage + flow.skeleton_storage
    stored = fem.assemble_scalar(fem.form(storage * (flow.p - flow.p_old) / dt * ufl.dx))
    stored = cpt.comm.allreduce(stored)
    inflow = flow.inflow("top")
    scale = cpt.comm.allreduce(fem.assemble_scalar(fem.form(storage * abs(flow.p - flow.p_old) / dt * ufl.dx)))
    assert scale > 0
    assert abs(inflow - stored) < 1e-8 * scale


def test_the_cone_alone_raises_a_positive_pressure_pushing_it_back(pushed):
    """The cone's solid moving down into grains at rest: the solid velocity converges at its
    faces (a positive source; where the grains' share of a cell varies the blended velocity
    diverges a little too, so p is not positive everywhere: measured 1830 Pa at most, -278
    Pa at least; 3D 111 / -5 Pa), the top drained and the other sides closed: the pressure
    is largest below the tip, positive there, and its push on the cone is up."""
    cpt, first = pushed
    assert first["u_max"] > 0 and first["u_max"] > 2 * abs(first["p_min"])
    assert first["below_tip"] > 0
    assert first["q_u"] > 0
    record = cpt.history[-1]
    assert record["q_t"] == pytest.approx(record["q_c"] + record["q_u"])


def test_u2_rises_from_drained_to_undrained():
    """The same push at V = 0.015 (k = 1e-9: drained) and V = 154 (k = 1e-13: undrained):
    the excess pressure at the shoulder is positive in the contractive window and far above
    the drained one (measured 9.2 kPa against 34 Pa)."""
    def u2(k):
        s = scene({"permeability": k})
        cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
        cpt.run()
        embedded = tip_height(cpt.prm) + cpt.prm.radius   # u2's point below the surface
        h = [r for r in cpt.history if r["depth"] > embedded]
        assert len(h) >= 5
        return cpt.normalised_velocity(), np.mean([r["u2"] for r in h])

    (V_drained, drained), (V_undrained, undrained) = u2(1e-9), u2(1e-13)
    assert V_drained < 0.3 < 30 < V_undrained
    assert undrained > 0
    assert undrained > 20 * abs(drained)


def continuum_strain_ratio(k, continuum):
    """The continuum's volumetric over deviatoric strain (their magnitudes integrated over
    the nodes beyond the overlap, w = 0) after the small scene's push."""
    s = scene({"permeability": k, "continuum": continuum})
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    cpt.run()
    u = cpt.problem.split(cpt.problem.w)[0]
    alone = fem.Function(cpt.flow.Vn)
    alone.x.array[:] = cpt.flow.weight.x.array == 0.0
    eps = ufl.sym(ufl.grad(u))

    def integral(f):
        return cpt.comm.allreduce(fem.assemble_scalar(fem.form(alone * f * ufl.dx)))
    return integral(abs(ufl.tr(eps))) / integral(ufl.sqrt(ufl.inner(ufl.dev(eps), ufl.dev(eps))))


def test_the_continuum_takes_the_pore_pressure():
    """fluid.continuum = "biot" (the default): the continuum beyond the overlap in total
    stress. Undrained (V = 154) it deforms nearly isochorically, its volumetric strain a
    sixth of its deviatoric one (measured 0.17), where the drained continuum of the same
    push took 0.81; drained (V = 0.015) as the dry one (0.83 and 0.87)."""
    undrained = continuum_strain_ratio(1e-13, "biot"), continuum_strain_ratio(1e-13, "drained")
    drained = continuum_strain_ratio(1e-9, "biot"), continuum_strain_ratio(1e-9, "drained")
    assert undrained[0] < 0.35 * undrained[1]
    assert drained[0] > 0.8 * drained[1]


def test_a_biot_continuum_needs_a_compressible_fluid_and_an_elastic_implicit_continuum():
    with pytest.raises(SceneError, match=r"fluid\.compressibility must be > 0 with fluid\.continuum = 'biot'"):
        scene({"compressibility": 0.0})
    assert scene({"compressibility": 0.0, "continuum": "drained"}).fluid_parameters().compressibility == 0
    with pytest.raises(SceneError, match="fluid.continuum = 'biot' takes the implicit micropolar"):
        scene({}, continuum={"integrator": "explicit"}).fluid_parameters()
    with pytest.raises(SceneError, match="continuum.model = 'micropolar_drucker_prager'"):
        scene({}, continuum={"model": "micropolar_drucker_prager"}).fluid_parameters()


def test_a_chambers_surcharge_stays_beside_the_fluids_forces(fast):
    """The DEM holds one set of external forces: a chamber's surcharge on its top grains, set
    before the fluid, is handed back with the fluid's forces at every fluid step."""
    cpt, _ = fast
    sim = cpt.sim
    top = np.flatnonzero(sim.p.kind[:cpt.n_grains] == 0)[:5]
    load = np.tile([0.0, -0.3, 0.0], (5, 1))
    sim.set_external_force(top, load)
    flow = ChamberFlow(cpt, cpt.fluid)
    flow.step(cpt.fluid.every * sim.dt)
    rows, f = sim.external_force()
    at = np.searchsorted(rows, top)
    assert np.array_equal(rows[at], top)
    np.testing.assert_allclose(f[at], flow.forces[top] + load, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("dim, k", [(2, 1e-11), (2, 1e-22), (3, 1e-11)])
def test_the_interval_force_is_the_next_fluid_steps_response(dim, k):
    """With a fluid step every few DEM steps the grains take, at every DEM step between,
    the force change their displacement du since the last fluid step makes
    (`ChamberFlow.interval_forces`): it is the next fluid step's response to du (the
    difference of two next steps, from the grains moved and from the grains where they
    were), to round-off in the pressure (~1e-16 measured) and to the hand-out's own change
    with the grains' positions in the forces (du 1e-9 m: 6e-7 measured); the same with flow
    (k = 1e-11) and undrained (k -> 0, where it is the fluid's storage stiffness alone).
    It resists a compaction (negative work). With the grains still, the interval's
    pressure change at its end is the next step's drainage of the last pressure. 2D and
    3D."""
    s = scene({"saturation_time": 0.0, "every": 10}, dim)
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    flow, sim = cpt.flow, cpt.sim
    assert flow.drag is None      # (every > 1: the interval's forces, no group drag)
    flow.cone_speed = 0.0
    cpt.stepper.v.x.array[:] = 0.0    # (the continuum at rest: the grains the only source)
    flow.set_permeability(k)
    dt = cpt.fluid.every * sim.dt
    flow.step(dt)
    # the grains still, the last pressure drains: at the interval's end the change is the
    # next step's (the cone still and the continuum at rest: no other source)
    p1 = flow.p.x.array.copy()
    flow.interval_forces(dt)
    drained = flow._work("interval_dp", flow.Vp).x.array.copy()
    flow.step(dt)
    if k > 1e-20:                          # (k -> 0: nothing drains)
        assert np.abs(flow.p.x.array - p1).max() > 1e-3 * np.abs(p1).max()
    np.testing.assert_allclose(drained, flow.p.x.array - p1, rtol=0, atol=1e-9 * np.abs(p1).max())
    # then from p = 0, du alone (the moved grains' storage n beta_f times the last pressure's
    # drainage would join du's own response)
    flow.p.x.array[:] = 0.0
    x0, p0 = sim.p.x.copy(), flow.p.x.array.copy()
    window = flow._grain_weight(x0[:cpt.n_grains, :dim]) >= 1.0
    inner = np.flatnonzero(window & (sim.p.kind[:cpt.n_grains] == FREE))
    r = x0[inner, :dim] - x0[inner, :dim].mean(axis=0)
    du = np.zeros_like(x0)
    du[inner, :dim] = -1e-9 * r / 0.01 * np.exp(-(r**2).sum(axis=1) / 0.01**2)[:, None]   # a compaction

    def next_step(x):
        sim.p.x[:] = x
        flow.step(dt)
        out = flow.p.x.array.copy(), flow.forces.copy()
        sim.p.x[:] = x0                                # back to the last step's state
        flow.p.x.array[:] = p0
        flow._x_last = x0[:cpt.n_grains].copy()
        flow.step(dt)
        flow.p.x.array[:] = p0
        flow._x_last = x0[:cpt.n_grains].copy()
        return out

    (p_still, f_still), (p_moved, f_moved) = next_step(x0), next_step(x0 + du)
    sim.p.x[:] = x0 + du
    predicted = flow.interval_forces(dt)
    dp = flow._work("interval_dp", flow.Vp).x.array
    scale = np.abs(p_moved - p_still).max()
    assert scale > 0
    np.testing.assert_allclose(dp, p_moved - p_still, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(predicted, f_moved - f_still, rtol=0,
                               atol=1e-5 * np.abs(f_moved - f_still).max())
    assert (du * predicted).sum() < 0


def test_a_grain_outside_the_window_takes_no_seepage_force():
    """The grains carry the skeleton by their weight w (1 in the window, 0 beyond the ghost
    band): a grain that strays into the continuum feels its buoyancy alone, not the whole
    node's seepage force (which it took before, and which flung grains out of the mesh)."""
    s = scene({"saturation_time": 0.0})
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    flow, sim = cpt.flow, cpt.sim
    flow.step(cpt.fluid.every * sim.dt)
    x = sim.p.x[:cpt.n_grains]
    i = int(np.flatnonzero(sim.p.kind[:cpt.n_grains] == FREE)[np.argmax(x[sim.p.kind[:cpt.n_grains] == FREE, 1]
                                                                   < -0.02)])
    stray = x[i].copy()
    stray[0] = 0.06                                     # beyond the window's band, in the mesh
    assert flow._grain_weight(stray[None, :2])[0] == 0.0
    sim.p.x[i] = stray
    flow.step(cpt.fluid.every * sim.dt)
    buoyancy = -flow.params.density * flow.volume[i] * sim.gravity
    np.testing.assert_allclose(flow.forces[i], buoyancy, rtol=1e-12, atol=1e-15)
    inside = np.flatnonzero(flow._grain_weight(x[:, :2]) >= 1.0)
    seepage = flow.forces[inside] + flow.params.density * flow.volume[inside, None] * sim.gravity
    assert np.abs(seepage).max() > 0                    # (the window's grains do feel it)


@pytest.mark.mpi
@pytest.mark.parametrize("dim", [2, 3])
def test_ranks_equal_serial(dim):
    """The saturated window's fluid (no saturation time: the same grains on every rank count):
    the cone-only step's readings and every grain's fluid force on all ranks equal a COMM_SELF
    run to round-off. (Pushed, the runs part: the grains' fluid forces are summed over the
    ranks in another order and the packings are chaotic; measured 5e-4 relative in the
    grains' forces after 100 DEM steps.) 2D and 3D."""
    s = scene({"saturation_time": 0.0}, dim)

    def build(comm):
        cpt = _set_up(s.parameters(), comm, quiet, None, None, None, s.fluid_parameters())
        first = cone_only(cpt)
        return [np.array([first[k] for k in ("u1", "u_max", "q_u", "below_tip", "p_min")]),
                cpt.flow.forces.copy()]

    serial, ranks = build(MPI.COMM_SELF), build(MPI.COMM_WORLD)
    for a, b in zip(serial, ranks, strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-10 * np.abs(a).max())


@pytest.mark.mpi
def test_interval_forces_ranks_equal_serial():
    """The interval's forces (a fluid step every 10 DEM steps) of the same displacement on
    all ranks equal a COMM_SELF run to round-off."""
    s = scene({"saturation_time": 0.0, "every": 10})

    def build(comm):
        cpt = _set_up(s.parameters(), comm, quiet, None, None, None, s.fluid_parameters())
        flow, sim = cpt.flow, cpt.sim
        dt = cpt.fluid.every * sim.dt
        flow.step(dt)
        rng = np.random.default_rng(3)         # (the same displacement on every rank)
        free = np.flatnonzero(sim.p.kind[:cpt.n_grains] == FREE)
        sim.p.x[free, :2] += 1e-7 * rng.standard_normal((len(free), 2))
        return flow.interval_forces(dt)

    serial, ranks = build(MPI.COMM_SELF), build(MPI.COMM_WORLD)
    assert np.abs(serial).max() > 0
    np.testing.assert_allclose(ranks, serial, rtol=0, atol=1e-8 * np.abs(serial).max())


def response_equals_interval_forces(dim):
    """The DEM's linear response at the k-th DEM step after a fluid step adds
    ``interval_forces(k dt)`` (to 1e-9 of it)."""
    s = scene({"saturation_time": 0.0, "every": 10}, dim)
    cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
    flow, sim = cpt.flow, cpt.sim
    flow.step(cpt.fluid.every * sim.dt)
    rng = np.random.default_rng(5)
    free = np.flatnonzero(sim.p.kind[:cpt.n_grains] == FREE)
    sim.p.x[free, :dim] += 1e-7 * rng.standard_normal((len(free), dim))
    response = flow.interval_response()
    rows = response.rows
    for k in (1, 2, 3):
        response.apply(sim)
        f = flow.interval_forces(k * sim.dt)[rows]
        f[sim.p.kind[rows] != FREE] = 0.0
        assert np.abs(f).max() > 0
        np.testing.assert_allclose(response.force, f, rtol=0, atol=1e-9 * np.abs(f).max())
    response.withdraw(sim)


def test_the_dems_response_is_the_interval_forces_in_3d():
    response_equals_interval_forces(3)


@pytest.mark.parametrize("stride", [1, 2])
def test_the_dem_takes_the_interval_response_in_its_fused_loop(monkeypatch, stride):
    """On one rank the DEM steps between fluid steps take the interval's forces as the DEM's
    linear response (`ChamberFlow.interval_response`, in the fused step loop): at the k-th
    DEM step after a fluid step it adds ``interval_forces(k dt)`` to round-off (SuperLU's
    factors for PETSc's: 1e-9 measured to ~1e-13), and a push through it equals a push
    through the interval hook (the Python step loop; the path of 2 ranks) to round-off of
    the same, grown by the chaotic packing over 3 FE steps (1e-6 of q_c), also with the
    forces' impulse once in 2 DEM steps (``fluid.response_every``, the stride; this small
    window's step takes no more: s dt omega 0.39)."""
    response_equals_interval_forces(2)

    def push(hooked):
        s = scene({"every": 10, "response_every": stride})
        cpt = _set_up(s.parameters(), MPI.COMM_WORLD, quiet, None, None, None, s.fluid_parameters())
        if hooked:   # an exchange hook (one that does nothing) takes the Python loop
            plain = cpt._before_sub_cycle
            monkeypatch.setattr(cpt, "_before_sub_cycle", lambda hook: plain(lambda: False))
        calls = []
        step = cpt.sim.step
        monkeypatch.setattr(cpt.sim, "step", lambda n, **kw: calls.append(kw) or step(n, **kw))
        q = [cpt.advance()["q_c"] for _ in range(3)]
        assert ("response" in calls[-1]) != hooked and calls[-1]["pause_every"] == 10
        return np.array(q)

    fused, hooked = push(False), push(True)
    assert np.abs(fused).max() > 0
    np.testing.assert_allclose(fused, hooked, rtol=1e-6)


def test_the_stride_fits_the_fluids_stiffest_mode(monkeypatch):
    """``fluid.response_every`` is the most: the run takes the largest divisor s of
    ``fluid.every`` up to it with s dt omega <= 0.5, omega the interval's stiffest frequency
    (`ChamberFlow.stiffest`, power iteration: the largest |eigenvalue| of M^-1 G from the
    dense G built column by column from interval_forces, to 1e-4: 40 iterations reach
    1.5e-5); this small window's
    step (omega dt ~ 0.2) takes 2 of 5, and 1 under a lowered limit."""
    s = scene({"every": 10, "response_every": 5})
    cpt = SaturatedPenetration(s.parameters(), s.fluid_parameters(), MPI.COMM_WORLD, log=quiet)
    cpt.advance()
    flow, sim = cpt.flow, cpt.sim
    omega = flow.stiffest()
    assert cpt.stride == 2 and 2 * omega * sim.dt <= 0.5 < 5 * omega * sim.dt
    free = np.flatnonzero(sim.p.kind[:cpt.n_grains] == FREE)
    x, h = sim.p.x.copy(), 1e-9      # (the forces are linear in x: any step)
    sim.p.x[free, :2] = flow._x_last[free, :2]
    base = flow.interval_forces(sim.dt)[free, :2].ravel()
    G = np.empty((2 * len(free), 2 * len(free)))
    for k in range(2 * len(free)):
        sim.p.x[free[k // 2], k % 2] += h
        G[:, k] = -(flow.interval_forces(sim.dt)[free, :2].ravel() - base) / h
        sim.p.x[free[k // 2], k % 2] = flow._x_last[free[k // 2], k % 2]
    sim.p.x[:] = x
    lam = np.abs(np.linalg.eigvals(G / np.repeat(sim.p.mass[free], 2)[:, None])).max()
    assert omega == pytest.approx(np.sqrt(lam), rel=1e-4)
    lowered = SaturatedPenetration(s.parameters(), s.fluid_parameters(), MPI.COMM_WORLD, log=quiet)
    monkeypatch.setattr(SaturatedPenetration, "STRIDE_LIMIT", 1e-4)
    lowered.advance()
    assert lowered.stride == 1


@pytest.mark.mpi
@pytest.mark.parametrize("every, stride", [(1, 1), (10, 1), (10, 2)])
def test_a_restart_repeats_the_saturated_run(tmp_path_factory, every, stride):
    """A saturated push restarted from a checkpoint repeats the straight run to the bit (q_c,
    u2, the pressure and the grains), with a fluid step every DEM step (the implicit drag)
    and every 10 (the DEM's linear response on one rank, the interval hook on two; its
    impulse every DEM step and once in 2): the
    checkpoint holds the pressure, the fluid's reference positions, where its points were
    located, the DEM's external forces and the interval force in the grains' forces. A dry
    run's checkpoint is refused by name."""
    comm = MPI.COMM_WORLD
    where = comm.bcast(str(tmp_path_factory.mktemp("cptu_ck")) if comm.rank == 0 else None, root=0)
    s = scene({"every": every, "response_every": stride})
    prm, fluid = s.parameters(), s.fluid_parameters()
    cpt = SaturatedPenetration(prm, fluid, comm, log=quiet)
    cpt.run(steps=2)
    cpt.save_checkpoint(f"{where}/ck")
    straight = [cpt.advance() for _ in range(3)]
    again = SaturatedPenetration(prm, fluid, comm, log=quiet, checkpoint=f"{where}/ck")
    assert len(again.history) == 2
    restarted = [again.advance() for _ in range(3)]
    for a, b in zip(straight, restarted, strict=True):
        for key in ("q_c", "u2", "u_max", "q_t"):
            assert a[key] == b[key], (key, a[key], b[key])
    assert np.array_equal(cpt.flow.p.x.array, again.flow.p.x.array)
    assert np.array_equal(cpt.sim.p.x, again.sim.p.x)
    assert np.array_equal(cpt.sim.p.force, again.sim.p.force)
    assert abs(straight[-1]["u_max"]) > 0
    dry = CoupledPenetration(prm, comm, log=quiet)
    dry.save_checkpoint(f"{where}/dry")
    with pytest.raises(FileNotFoundError, match="no pore fluid"):
        SaturatedPenetration(prm, fluid, comm, log=quiet, checkpoint=f"{where}/dry")
