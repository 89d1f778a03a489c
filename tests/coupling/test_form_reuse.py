"""Two coupled penetrations that differ only in their packing reuse the continuum's compiled
forms: the packing's numbers (density, the surface's height, K0, the moduli) reach the forms
as ``fem.Constant``, so no FFCx signature holds them (a float in a form would compile every
form that holds it again, minutes for the plastic micromorphic continuum).

The spy wraps FFCx's cache look-up (``ffcx.codegeneration.jit.get_cached_module``), which
every form and expression compilation passes with its module name, the hash of its
signature: it counts real look-ups, whether the disk cache already holds the module or not.
"""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import ffcx.codegeneration.jit as ffcx_jit
import pytest
from test_micromorphic_coupling import TINY  # its small micromorphic pile (a few hundred spheres)


def modules_built(monkeypatch, build) -> list[str]:
    """The FFCx modules (forms and expressions) ``build()`` compiles or loads."""
    names, look_up = [], ffcx_jit.get_cached_module

    def spy(module_name, *args, **kwargs):
        names.append(module_name)
        return look_up(module_name, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(ffcx_jit, "get_cached_module", spy)
        build()
    return names


@pytest.mark.parametrize("continuum", ["micromorphic", "micropolar"])
def test_a_new_packing_compiles_no_new_form(monkeypatch, continuum):
    """The 3D pile on a free surface (gravity and the geostatic side traction), one FE step
    of two packings (seeds 0 and 1): the second needs no module the first did not."""
    from coupling.apps.penetration.coupled import CoupledPenetration, PenetrationParameters

    runs = []

    def run(seed):
        prm = PenetrationParameters(**(TINY | dict(continuum=continuum)), shape="pile", seed=seed)
        cpt = CoupledPenetration(prm, MPI.COMM_SELF, log=lambda m: None)
        cpt.run(steps=1)
        runs.append(cpt)

    first = modules_built(monkeypatch, lambda: run(0))
    second = modules_built(monkeypatch, lambda: run(1))
    assert first and second, "the spy saw no compilation: FFCx's JIT no longer passes get_cached_module"
    assert set(second) <= set(first), f"compiled again for the second packing: {sorted(set(second) - set(first))}"
    # the packings differ in the numbers the forms read, each run holding its own
    a, b = (cpt.geostatic for cpt in runs)
    assert a.surface.value != b.surface.value and a.unit_weight.value != b.unit_weight.value
    for cpt in runs:
        m = cpt.material_fe
        assert cpt.geostatic.unit_weight.value == m.rho * cpt.prm.gravity
        assert cpt.geostatic.surface.value == cpt.surface and cpt.geostatic.k0.value == cpt._geostatic_k0()
