"""The application table: every row resolves, scenes load through it, and a new
application is one row (shown with a toy application registered for the test only)."""

import dataclasses
import json

import pytest

from coupling import applications
from coupling import scene as scene_module
from coupling.applications import APPLICATIONS, Application, application
from coupling.scene import SceneError, load_scene


@pytest.mark.parametrize("kind", sorted(APPLICATIONS))
def test_every_row_resolves(kind):
    app = APPLICATIONS[kind]
    assert app.kind == kind
    for role in ("scene", "summarise", "run", "checks"):
        target = app.load(role)
        assert target is None if getattr(app, role) is None else callable(target)
    assert dataclasses.is_dataclass(app.load("scene"))


def test_unknown_kind_is_refused_by_key(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('[scene]\nkind = "triaxial"\n')
    with pytest.raises(SceneError, match=r"scene.kind must be one of \['bonded_punch', 'penetration'\]"):
        load_scene(path)
    with pytest.raises(ValueError, match="scene.kind"):
        application("triaxial")


@dataclasses.dataclass(frozen=True)
class Toy:
    steps: int = 3


@dataclasses.dataclass(frozen=True)
class ToyScene:
    """A scene of one section besides [scene]: the whole of a toy application."""

    scene: scene_module.SceneInfo = dataclasses.field(
        default_factory=lambda: scene_module.SceneInfo(name="toy", kind="toy"))
    toy: Toy = dataclasses.field(default_factory=Toy)


def summarise_toy(scene, ranks=1):
    return {"kind": "toy", "steps": scene.toy.steps, "memory_estimate_MB_per_rank": 1.0,
            "memory_driver": "toy.steps"}


def run_toy(scene, out, comm, *, progress=True, checkpoint=None, stop=None, meta=None):
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"steps": scene.toy.steps}))


def test_a_new_application_is_one_row(tmp_path, monkeypatch):
    from coupling.preflight import preflight

    row = Application(kind="toy", dimensions=(2,), default_name="toy",
                      scene=f"{__name__}:ToyScene", summarise=f"{__name__}:summarise_toy",
                      run=f"{__name__}:run_toy")
    monkeypatch.setitem(APPLICATIONS, "toy", row)
    monkeypatch.setattr(scene_module, "KINDS", tuple(APPLICATIONS))
    path = tmp_path / "toy.toml"
    path.write_text('[scene]\nkind = "toy"\n[toy]\nsteps = 5\n')
    scene = load_scene(path)
    assert scene.toy.steps == 5 and scene.scene.name == "toy"
    assert applications.summarise(scene)["steps"] == 5
    assert preflight(scene)["warnings"] == []
    application("toy").load("run")(scene, tmp_path / "out", None)
    assert json.loads((tmp_path / "out" / "results.json").read_text()) == {"steps": 5}
