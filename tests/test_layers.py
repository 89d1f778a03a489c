"""The import layers: applications -> coupling method -> {granfe, dem}.

``granfe`` knows nothing of particles, ``dem`` nothing of the finite elements, and the
bridging-scale method in ``coupling`` nothing of any application built on it. Read from
the source (every import statement, at any depth), so a lazy import inside a function
counts too.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FE_STACK = {"dolfinx", "dolfinx_solver", "ufl", "basix", "petsc4py", "ffcx", "adios4dolfinx"}
# the bridging-scale method; every other module of coupling/ is an application or a tool
# that serves applications (scenes, runner, command line)
METHOD = {"__init__", "locate", "operators", "regions", "interface", "micro_kinematics", "staggered", "dynamic",
          "monolithic1d", "substep"}


def imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
    return found


def modules(package: str):
    return sorted((ROOT / package).rglob("*.py"))


def top(name: str) -> str:
    return name.split(".")[0]


@pytest.mark.parametrize("path", modules("granfe"), ids=lambda p: str(p.relative_to(ROOT)))
def test_granfe_imports_no_particles(path):
    bad = {m for m in imports(path) if top(m) in ("dem", "coupling")}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("path", modules("dem"), ids=lambda p: str(p.relative_to(ROOT)))
def test_dem_imports_no_finite_elements(path):
    bad = {m for m in imports(path) if top(m) in FE_STACK | {"granfe", "coupling", "meshes"}}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("path", [p for p in modules("coupling") if p.stem in METHOD
                                  and p.parent.name == "coupling"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_coupling_method_imports_no_application(path):
    bad = {m for m in imports(path)
           if top(m) == "coupling" and m.split(".")[1:2] and m.split(".")[1] not in METHOD}
    bad |= {m for m in imports(path) if top(m) == "meshes"}
    assert not bad, f"{path.relative_to(ROOT)} (coupling method) imports {sorted(bad)}"


def test_the_method_list_names_real_modules():
    present = {p.stem for p in modules("coupling")}
    assert METHOD - {"substep"} <= present, METHOD - present


def test_the_layer_check_can_fail(tmp_path):
    bad = tmp_path / "x.py"
    bad.write_text("def f():\n    from dolfinx import fem\n")
    assert "dolfinx" in imports(bad)


SERVING = {"scene", "cli", "preflight", "rundir", "checkpoints", "interrupts", "applications"}


@pytest.mark.parametrize("path", [p for p in modules("coupling") if p.stem in SERVING
                                  and p.parent.name == "coupling"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_what_serves_the_applications_names_none(path):
    """Scenes, the command line and checks reach an application only through the table of
    coupling.applications (as strings), never by import."""
    bad = {m for m in imports(path) if m.startswith("coupling.apps")}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("path", sorted((ROOT / "coupling" / "apps").rglob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_applications_do_not_import_each_other(path):
    own = path.relative_to(ROOT / "coupling" / "apps").parts[0]
    bad = {m for m in imports(path)
           if m.startswith("coupling.apps.") and m.split(".")[2] != own}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"
