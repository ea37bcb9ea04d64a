"""Reading a picture of an asset whose textures an import changed (`meshseal.reading.imports`): the
prediction is made from the original's textures as that import makes them, picked by how well they
explain the picture, without a key."""

from pathlib import Path

import torch

from meshseal.api import load as load_model
from meshseal.evaluation import asset_attacks
from meshseal.mesh import load, normalize, to_z_up
from meshseal.reading import imports
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views

FIXTURES = Path(__file__).parent / "fixtures"


def test_imported_textures_are_the_asset_attacks_own():
    """The reading's halved candidate is `meshseal eval`'s `texture_half` attack."""
    texture = torch.rand(3, 32, 40, generator=torch.Generator().manual_seed(0))
    made = imports.imported_textures([texture, None])
    assert made["halved"][0].shape == (3, 16, 20) and made["halved"][1] is None
    assert made["quartered"][0].shape == (3, 8, 10)
    expected = asset_attacks.texture_resize(0.5)
    from meshseal.mesh import Material, Mesh

    mesh = Mesh(torch.zeros(3, 3), None, torch.tensor([[0, 1, 2]]), torch.zeros(3, 2),
                materials=[Material(texture=texture.permute(1, 2, 0))])
    assert torch.equal(expected(mesh, None).materials[0].texture.permute(2, 0, 1), made["halved"][0])
    assert set(made) == {"halved", "quartered"}


def _picture(mesh, size=256):
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    with torch.no_grad():
        image = MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(mesh))), cameras, lights, size, size).image
    return (torch.round(image.clamp(0, 1) * 255) / 255)[0].permute(1, 2, 0).numpy(), cameras


def _read_recording(pick: str, wm, original, shown: dict) -> tuple[list, dict]:
    """Each picture of `shown` (name -> Mesh) read against `original`, with what `imports.<pick>` chose
    for each, in order: (choices, name -> Detection)."""
    picked, real_pick = [], getattr(imports, pick)

    def recording(*args, **kwargs):
        picked.append(real_pick(*args, **kwargs))
        return picked[-1]

    setattr(imports, pick, recording)
    try:
        results = {}
        for name, mesh in shown.items():
            picture, cameras = _picture(mesh)
            results[name] = wm.decide([wm.read(picture, original, camera=cameras)])
    finally:
        setattr(imports, pick, real_pick)
    return picked, results


def test_a_picture_of_an_asset_with_halved_textures_reads_against_the_halved_original():
    """The marked bunny's texture halved (an engine's size cap) before its picture: the reading picks
    'halved' and reads the message; its clean picture picks the textures as given; a picture of the
    unmarked bunny with halved textures is not detected (the pick itself finds no mark)."""
    wm = load_model("default")
    assert wm.model.config.read_imports
    bunny = load(FIXTURES / "bunny.glb")
    original = wm.original(bunny)
    marked = wm.embed(bunny, "ab42")
    halve = asset_attacks.texture_resize(0.5)
    picked, results = _read_recording("pick", wm, original, {"clean": marked, "halved": halve(marked, None),
                                                             "unmarked": halve(bunny, None)})
    assert picked == [None, "halved", "halved"]
    assert results["clean"].detected and results["clean"].message == "ab42"
    assert results["halved"].detected and results["halved"].message == "ab42"
    assert not results["unmarked"].detected and results["unmarked"].p_value > 1e-3


def test_without_read_imports_the_textures_are_taken_as_given():
    wm = load_model("default")
    wm.model.config.read_imports = False
    try:
        assert wm.method.imports_of(wm.original(load(FIXTURES / "bunny.glb"))) is None
    finally:
        wm.model.config.read_imports = True


def test_recomputed_normals_are_a_candidate_only_where_they_differ():
    """A prepared original whose normals are those its faces give has no normals candidate; one with
    authored normals (the bunny's) has them recomputed as the loader recomputes them."""
    from dataclasses import replace

    from meshseal.mesh.preprocess import vertex_normals

    wm = load_model("default")
    original = wm.original(load(FIXTURES / "bunny.glb"))
    made = imports.imported(original)
    assert made.normals is not None and made.normals.shape == original.normals.shape
    assert torch.allclose(made.normals[0], vertex_normals(original.positions[0], original.faces.reshape(-1, 3)))
    assert imports.imported(replace(original, normals=made.normals)).normals is None
    assert set(made.textures) == {"halved", "quartered"}


def test_a_picture_of_a_converted_asset_reads_against_the_recomputed_normals():
    """Suzanne marked, then converted GLB -> OBJ by trimesh (`obj_glb`: its normals recomputed from the
    faces on loading): the reading picks the recomputed normals and reads the message; the clean
    picture keeps the given ones; the unmarked suzanne converted is not detected."""
    wm = load_model("default")
    suzanne = load(FIXTURES / "suzanne.glb")
    original = wm.original(suzanne)
    marked = wm.embed(suzanne, "ab42")
    picked, results = _read_recording("pick_normals", wm, original, {
        "clean": marked, "converted": asset_attacks.converted(marked, None),
        "unmarked": asset_attacks.converted(suzanne, None)})
    assert picked == [False, True, True]
    assert results["clean"].detected and results["clean"].message == "ab42"
    assert results["converted"].detected and results["converted"].message == "ab42"
    assert not results["unmarked"].detected and results["unmarked"].p_value > 1e-3


def test_a_picked_import_must_beat_the_textures_as_given_under_the_pictures_footprint():
    """`beats_footprint` keeps a picked import only where its point-sampled residual's detail is under
    PICK_BELOW of the textures as given under the picture's footprint (a halved picture: the area's
    prediction explains it; an asset with halved textures: the import does)."""
    from types import SimpleNamespace

    generator = torch.Generator().manual_seed(0)
    side = 32
    pixel = torch.arange(side * side)
    fragments = SimpleNamespace(pixel=pixel)
    keep = torch.arange(side * side)
    seen = torch.rand(side * side, 3, generator=generator)
    detail = torch.rand(side * side, 3, generator=generator) - 0.5  # what a prediction misses: fine detail

    def residual(expected):
        return SimpleNamespace(seen=seen, expected=expected, fragments=fragments, keep=keep)

    given = residual(seen + detail)  # point samples of the textures as given miss the detail
    shape = (1, side, side)
    area = SimpleNamespace(expected=seen + 0.1 * detail, usable=torch.ones(side * side, dtype=torch.bool))
    assert not imports.beats_footprint(residual(seen + 0.5 * detail), given, area, shape)  # the area explains more
    assert imports.beats_footprint(residual(seen + 0.05 * detail), given, area, shape)  # the import explains more
