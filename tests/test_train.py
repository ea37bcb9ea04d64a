"""Training, evaluation, the API and the model CLI end to end on a tiny dataset built from the fixtures."""

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import load_file

import meshseal
from meshseal.cli import main
from meshseal.errors import MeshsealError
from meshseal.data.build import build
from meshseal.models.io import load_model
from meshseal.training.train import TrainConfig, Trainer

FIXTURES = Path(__file__).parent / "fixtures"

TINY = {
    "name": "tiny", "seed": 3,
    "model": {"n_bits": 8, "strategy": "vertex+texture", "texture_channels": 8, "texture_blocks": 2,
              "texture_downsample": 2, "texture_tile": 4, "texture_size": 32, "decoder_channels": 8,
              "decoder_blocks": 4, "decoder_stem_stride": 2, "vertex_width": 8, "frame_size": 32},
    "loss": {"reg": 0.0001},
    "train": {"steps": 6, "pretrain_steps": 2, "batch_size": 2, "lr": 0.001, "render_size": 48,
              "background": "random", "warmup_steps": 4, "target_slack": 5.0, "target_psnr": 40.0,
              "target_psnr_texture": 30.0, "distortion_start": 3, "distortion_2d": 0.5, "retexture": 0.5,
              "val_every": 3, "val_meshes": 2, "checkpoint_every": 3},
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    src = root / "src"
    src.mkdir()
    for name in ("bunny.glb", "suzanne.glb", "multi_material.glb", "cube.off"):
        shutil.copy(FIXTURES / name, src / name)
    for name in ("teapot", "sh3d_crate"):
        shutil.copytree(FIXTURES / name, src / name)
    build(root / "data", sources=[], texture_sources=[], from_folder=src, textures_dir=FIXTURES / "textures",
          seed=0, n_faces=400, texture_size=32, workers=1, license_="CC0-1.0", test_fraction=0.3)
    return root / "data"


def _config(data, **train):
    values = json.loads(json.dumps(TINY))
    values["data"] = str(data)
    values["train"].update(train)
    return TrainConfig.from_dict(values)


def test_a_run_can_start_from_another_with_a_part_frozen(dataset, tmp_path):
    """The paper's Table 8: a texture encoder trained first, then kept fixed while the rest learns."""
    Trainer(_config(dataset, steps=2, val_every=2, checkpoint_every=2), tmp_path / "first", log=lambda *_: None).fit()
    first = load_model(tmp_path / "first" / "model.safetensors").state_dict()
    config = _config(dataset, steps=3, pretrain_steps=0, val_every=3, checkpoint_every=3,
                     init_from=str(tmp_path / "first" / "model.safetensors"), frozen=["texture_encoder"])
    Trainer(config, tmp_path / "second", log=lambda *_: None).fit()
    second = load_model(tmp_path / "second" / "model.safetensors").state_dict()
    weights = [k for k in first if first[k].is_floating_point() and "running" not in k]
    encoder = [k for k in weights if k.startswith("texture_encoder.")]
    assert encoder and all(torch.equal(first[k], second[k]) for k in encoder)
    assert any(not torch.equal(first[k], second[k]) for k in weights if k.startswith("decoder."))
    with pytest.raises(meshseal.MeshsealError, match="no spoiler"):
        Trainer(_config(dataset, frozen=["spoiler"]), tmp_path / "bad", log=lambda *_: None)


def test_a_run_continues_from_another_under_settings_that_hold_no_weights(dataset, tmp_path):
    """A run continued with a quieter mark starts from the first run's weights; another architecture is refused."""
    start = str(tmp_path / "first" / "model.safetensors")
    Trainer(_config(dataset, steps=2, val_every=2, checkpoint_every=2), tmp_path / "first", log=lambda *_: None).fit()
    quieter = _config(dataset, steps=1, pretrain_steps=0, init_from=start)
    quieter.model.texture_rms = TINY["model"].get("texture_rms", 0.0) + 0.01
    continued = Trainer(quieter, tmp_path / "second", log=lambda *_: None)
    first = load_model(start).state_dict()
    assert all(torch.equal(first[k], v.cpu()) for k, v in continued.model.state_dict().items())
    wider = _config(dataset, init_from=start)
    wider.model.decoder_channels += 8
    with pytest.raises(meshseal.MeshsealError, match="same architecture"):
        Trainer(wider, tmp_path / "wider", log=lambda *_: None)


def test_training_writes_logs_checkpoints_and_weights(dataset, tmp_path):
    summary = Trainer(_config(dataset), tmp_path / "run", log=lambda *_: None).fit()
    assert summary["steps"] == 6
    for name in ("log.csv", "val.csv", "curves.png", "checkpoint.safetensors", "model.safetensors", "summary.json"):
        assert (tmp_path / "run" / name).is_file(), name
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()
    assert len(rows) == 7 and rows[1].split(",")[1] == "1" and rows[-1].split(",")[1] == "2"
    assert len((tmp_path / "run" / "val.csv").read_text().splitlines()) == 3  # steps 3 and 6


def test_same_seed_same_numbers_and_resume_continues_exactly(dataset, tmp_path):
    Trainer(_config(dataset), tmp_path / "a", log=lambda *_: None).fit()
    Trainer(_config(dataset), tmp_path / "b", log=lambda *_: None).fit()
    log = lambda run: [r.split(",")[:5] for r in (tmp_path / run / "log.csv").read_text().splitlines()]  # noqa: E731
    assert log("a") == log("b")
    Trainer(_config(dataset, steps=3), tmp_path / "c", log=lambda *_: None).fit()
    Trainer(_config(dataset), tmp_path / "c", resume=True, log=lambda *_: None).fit()
    first, resumed = load_file(str(tmp_path / "a" / "model.safetensors")), load_file(str(tmp_path / "c" / "model.safetensors"))
    assert first.keys() == resumed.keys()
    for key in first:
        assert torch.allclose(first[key].float(), resumed[key].float(), atol=1e-6), key


def test_a_run_made_in_parts_with_stop_at_equals_the_run_made_at_once(dataset, tmp_path):
    """--stop-at ends a run early without changing its schedules, so the parts, resumed, give the whole run."""
    whole = Trainer(_config(dataset, lr_decay_from=2), tmp_path / "whole", log=lambda *_: None).fit()
    part = Trainer(_config(dataset, lr_decay_from=2, stop_at=4), tmp_path / "parts", log=lambda *_: None).fit()
    assert part["steps"] == 4 and whole["steps"] == 6
    Trainer(_config(dataset, lr_decay_from=2), tmp_path / "parts", resume=True, log=lambda *_: None).fit()
    first, second = (load_file(str(tmp_path / run / "model.safetensors")) for run in ("whole", "parts"))
    for key in first:
        assert torch.allclose(first[key].float(), second[key].float(), atol=1e-6), key


def _texture_config(data, **train):
    config = _config(data, **({"gbuffer_views": 2, "retexture": 0.0} | train))
    config.model.strategy = "texture"
    return config


def test_texture_models_train_on_cached_gbuffers_and_resume_exactly(dataset, tmp_path):
    """A texture-only blind model trains on baked views (no rasterizing in the step), the bake is kept
    beside the data and reused, and a resumed run ends where an uninterrupted one does."""
    quiet = lambda *_: None  # noqa: E731
    first = Trainer(_texture_config(dataset), tmp_path / "a", log=quiet)
    assert first.views is not None and len(first.views["train"]) == 2 * len(first.train_set)
    banks = sorted((dataset / "gbuffers").glob("*.npz"))
    assert len(banks) >= 2  # train and test (other tests' banks beside them)
    stamps = [bank.stat().st_mtime_ns for bank in banks]
    first.fit()
    rows = (tmp_path / "a" / "log.csv").read_text().splitlines()
    assert len(rows) == 7 and rows[-1].split(",")[1] == "2"
    assert len((tmp_path / "a" / "val.csv").read_text().splitlines()) == 3
    Trainer(_texture_config(dataset, steps=3), tmp_path / "c", log=quiet).fit()
    resumed = Trainer(_texture_config(dataset), tmp_path / "c", resume=True, log=quiet)
    resumed.fit()
    assert [bank.stat().st_mtime_ns for bank in banks] == stamps  # reused, not baked again
    log = lambda run: [r.split(",")[:5] for r in (tmp_path / run / "log.csv").read_text().splitlines()]  # noqa: E731
    assert log("a") == log("c")
    a, c = load_file(str(tmp_path / "a" / "model.safetensors")), load_file(str(tmp_path / "c" / "model.safetensors"))
    for key in a:
        assert torch.allclose(a[key].float(), c[key].float(), atol=1e-6), key


def test_supersampled_views_are_baked_larger_and_box_filtered_to_the_frame(dataset, tmp_path):
    """gbuffer_supersample k: views baked at k times the frame, each picture the k x k mean of the large one."""
    from meshseal.training.gbuffer import composite

    quiet = lambda *_: None  # noqa: E731
    trainer = Trainer(_texture_config(dataset, gbuffer_supersample=2, steps=1), tmp_path / "ss", log=quiet)
    frame = trainer.model.config.frame_size
    views = trainer.views["test"][:2]
    assert views.uv.shape[1] == 2 * frame
    message = torch.ones(2, trainer.model.n_bits)
    out = trainer._gbuffer_pass(views, "test", message, torch.zeros(2, 3))
    assert out["picture"].shape[-1] == frame
    large = composite(out["texture"], views, torch.zeros(2, 3))
    assert torch.allclose(out["original"], large.unflatten(2, (frame, 2)).unflatten(4, (frame, 2)).mean((3, 5)), atol=1e-6)
    assert trainer.fit()["steps"] == 1
    with pytest.raises(meshseal.MeshsealError, match="gbuffer_supersample"):
        Trainer(_texture_config(dataset, gbuffer_supersample=0), tmp_path / "none", log=quiet)


def test_channels_last_networks_train_to_the_same_numbers(dataset, tmp_path):
    """train.channels_last changes the weights' memory order, not what a step computes."""
    quiet = lambda *_: None  # noqa: E731
    runs = {}
    for nhwc in (False, True):
        trainer = Trainer(_texture_config(dataset, steps=2, channels_last=nhwc), tmp_path / str(nhwc), log=quiet)
        conv = next(m for m in trainer.model.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3))
        assert conv.weight.is_contiguous(memory_format=torch.channels_last) == nhwc
        trainer.fit()
        runs[nhwc] = load_file(str(tmp_path / str(nhwc) / "model.safetensors"))
    for key, value in runs[False].items():
        assert torch.allclose(value.float(), runs[True][key].float(), atol=1e-4), key


def test_vertex_marks_train_on_baked_views_too_and_informed_models_are_refused(dataset, tmp_path):
    """A vertex + texture mark trains on baked views that keep each pixel's face and barycentrics (the
    marked normals and uvs re-shade them); `gbuffer: off` renders every step; an informed decoder reads
    un-rendered UV maps, which no baked picture gives."""
    quiet = lambda *_: None  # noqa: E731
    assert Trainer(_texture_config(dataset, gbuffer="off", steps=1), tmp_path / "off", log=quiet).views is None
    both = Trainer(_config(dataset, steps=2, pretrain_steps=0, val_every=2, checkpoint_every=2, gbuffer_views=1),
                   tmp_path / "vertex", log=quiet)  # TINY is vertex + texture
    assert both.views is not None and both.views["train"].surface is not None
    before = {k: v.clone() for k, v in both.model.vertex_encoder.state_dict().items()}
    both.fit()
    assert len((tmp_path / "vertex" / "log.csv").read_text().splitlines()) == 3
    after = both.model.vertex_encoder.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)  # the vertex encoder learned
    informed = _config(dataset, gbuffer="on", pretrain_steps=0)
    informed.model.decoder = "uv"
    with pytest.raises(MeshsealError, match="gbuffer: on"):
        Trainer(informed, tmp_path / "on", log=quiet)


@pytest.mark.heavy
def test_two_processes_under_torchrun_train_as_one_at_the_same_global_batch(dataset, tmp_path):
    """Data-parallel training (gloo on the CPU): each process takes half of every global batch, the
    gradients are averaged and batch normalisation sees the global batch, so two processes end with
    the weights one process reaches."""
    import subprocess
    import sys

    import yaml

    config = _texture_config(dataset, steps=3, batch_size=4, pretrain_steps=0, distortion_2d=0.0, val_every=3,
                             checkpoint_every=3)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config.to_dict()))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    train = ["-m", "meshseal.cli", "train", "--config", str(path), "--device", "cpu", "--out"]
    subprocess.run([sys.executable, *train, str(tmp_path / "one")], check=True, env=env, capture_output=True)
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           *train, str(tmp_path / "two")], env=env, capture_output=True, text=True)
    clues = [line for line in done.stderr.splitlines() if any(word in line for word in ("terminate", "what()", "Error", "error:"))]
    assert done.returncode == 0, "\n".join(clues[:30]) + "\n" + done.stderr[-1500:]  # the first error, then torchrun's summary
    assert done.stdout.count('"steps": 3') == 1  # one process reports
    one, two = load_file(str(tmp_path / "one" / "model.safetensors")), load_file(str(tmp_path / "two" / "model.safetensors"))
    assert one.keys() == two.keys()
    for key in one:
        assert torch.allclose(one[key].float(), two[key].float(), atol=1e-5), key
    log = lambda run: [r.split(",")[:3] for r in (tmp_path / run / "log.csv").read_text().splitlines()]  # noqa: E731
    assert len(log("two")) == 4


def test_bad_configs_are_clear_errors(tmp_path):
    (tmp_path / "bad.yaml").write_text("model: {n_bits: 8}\ntrain: {no_such: 1}\n")
    assert main(["train", "--config", str(tmp_path / "bad.yaml")]) == 2
    (tmp_path / "broken.yaml").write_text("model: [\n")
    assert main(["train", "--config", str(tmp_path / "broken.yaml")]) == 2
    assert main(["train", "--config", str(tmp_path / "missing.yaml")]) == 2


def test_cli_embed_render_detect_eval_round_trip(dataset, tmp_path, capsys):
    Trainer(_config(dataset), tmp_path / "run", log=lambda *_: None).fit()
    model = str(tmp_path / "run" / "model.safetensors")
    capsys.readouterr()
    bits = "10110010"
    assert main(["embed", str(FIXTURES / "multi_material.glb"), "-o", str(tmp_path / "m.glb"),
                 "--bits", bits, "--model", model, "--json", "--views", "2"]) == 0
    report = json.loads(capsys.readouterr().out)
    for key in ("psnr_texture", "normal_angle_deg", "uv_shift_texels", "psnr_object", "ssim_object", "flip_object",
                "psnr_frame", "ssim_frame"):
        assert key in report
    assert 20 < report["psnr_object"] <= report["psnr_frame"] and 0 <= report["flip_object"] <= 1
    marked = meshseal.load_mesh(tmp_path / "m.glb")
    original = meshseal.load_mesh(FIXTURES / "multi_material.glb")
    assert torch.equal(marked.positions, original.positions) and marked.n_faces == original.n_faces
    assert main(["render", str(tmp_path / "m.glb"), "-o", str(tmp_path / "v.png"), "--width", "120",
                 "--height", "90"]) == 0
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "v.png"), "--model", model, "--json"]) == 0
    result = json.loads(capsys.readouterr().out.splitlines()[0])
    assert len(result["bits"]) == 8 and set(result["bits"]) <= {"0", "1"} and len(result["soft"]) == 8
    # A blind learned model of 8 bits has no payload schema and uncalibrated logits: bits, no decision.
    assert result["detected"] is None and result["p_value"] is None and result["message"] is None
    assert main(["eval", "--data", str(dataset), "--model", model, "--views", "2", "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    for key in ("bit_acc", "bit_acc_std", "psnr_object", "ssim_object", "flip_object", "psnr_render", "ssim_render",
                "psnr_texture", "l1_normal", "l1_uv", "n_meshes", "n_views"):
        assert key in metrics
    assert metrics["n_views"] == 2 and 0 <= metrics["bit_acc"] <= 1
    assert main(["eval", "--data", str(dataset), "--model", model, "--protocol", "seed", "--split", "all",
                 "--json"]) == 0
    seed_metrics = json.loads(capsys.readouterr().out)
    assert seed_metrics["protocol"] == "seed" and seed_metrics["texture_kinds"] == ["noise", "real"]
    assert seed_metrics["sampler"] == "seed" and seed_metrics["n_meshes"] >= 1
    # Bad input: wrong message length, not bits, unreadable image, a mesh that can't carry the mark.
    for argv in (["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "x.glb"), "--bits", "101", "--model", model],
                 ["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "x.glb"), "--bits", "abcdefgh", "--model", model],
                 ["embed", str(FIXTURES / "bunny.glb"), "-o", str(FIXTURES / "bunny.glb"), "--bits", bits, "--model", model],
                 ["detect", str(FIXTURES / "LICENSES"), "--model", model],
                 ["eval", "--data", str(tmp_path), "--model", model],
                 ["eval", "--data", str(dataset), "--model", model, "--protocol", "seed", "--sampler", "any"],
                 ["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "x.glb"), "--bits", bits, "--model", "nope"]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("meshseal: error:") and "Traceback" not in err[0], argv


def test_api_detect_accepts_arrays_any_size_and_alpha(dataset, tmp_path):
    Trainer(_config(dataset), tmp_path / "run", log=lambda *_: None).fit()
    wm = meshseal.load(str(tmp_path / "run" / "model.safetensors"))
    assert wm.n_bits == 8
    picture = np.zeros((300, 500, 4), dtype=np.uint8)
    picture[100:200, 150:260] = (200, 120, 40, 255)
    for image in (picture, picture[..., :3], Image.fromarray(picture), torch.from_numpy(picture[..., :3]).float() / 255):
        result = wm.detect(image)
        assert len(result.bits) == 8 and len(result.soft) == 8
    assert isinstance(wm.detect([picture, picture]), list)


def test_finetune_caches_tunes_only_the_decoder_and_resumes(dataset, tmp_path):
    from meshseal.data.dataset import MeshDataset
    from meshseal.training.finetune import FinetuneConfig, finetune

    Trainer(_config(dataset), tmp_path / "run", log=lambda *_: None).fit()
    model = load_model(tmp_path / "run" / "model.safetensors")
    cfg = FinetuneConfig(engine="gl", meshes=2, views=1, size=48, steps=4, batch=2, lr=1e-2, val_meshes=1,
                         engines=["ours", "gl"], save_every=2, tolerance=1.0)
    train_set, test_set = MeshDataset(dataset, "train"), MeshDataset(dataset, "test")
    report = finetune(model, train_set, test_set, cfg, tmp_path / "ft", log=lambda *_: None)
    assert report["kept"] and set(report["before"]) == set(report["after"]) == {"ours", "gl"}
    assert report["train_pictures"] == 2
    cached = sorted((tmp_path / "ft" / "cache" / "gl").glob("*.npz"))
    assert len(cached) == 2
    tuned = load_model(tmp_path / "ft" / "model.safetensors")
    before, after = model.state_dict(), tuned.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("decoder.") for k in changed)  # only the decoder learned
    stamps = [p.stat().st_mtime_ns for p in cached]
    again = finetune(model, train_set, test_set, cfg, tmp_path / "ft", log=lambda *_: None)  # resumes: done
    assert [p.stat().st_mtime_ns for p in cached] == stamps  # the cache was reused, not re-rendered
    assert again["after"] == report["after"]


def test_finetune_refuses_a_matched_filter(dataset, tmp_path):
    from meshseal.data.dataset import MeshDataset
    from meshseal.training.finetune import FinetuneConfig, finetune

    with pytest.raises(meshseal.MeshsealError, match="nothing to fine-tune"):
        finetune(meshseal.load().model, MeshDataset(dataset, "train"), MeshDataset(dataset, "test"),
                 FinetuneConfig(engine="gl"), tmp_path / "ft")


def test_registered_eval_counts_refused_pictures_and_stays_strict_json(dataset, monkeypatch):
    """A picture `meshseal detect` refuses counts at chance and as infinitely off in the quantiles; the
    report stays strict JSON (no Infinity or NaN) when every picture is refused."""
    from meshseal.evaluation import evaluate as E
    from meshseal.data.dataset import MeshDataset

    reading = E._read_or_none
    monkeypatch.setattr(E, "_read_or_none", lambda w, p, o, **options:
                        None if options.get("register") else reading(w, p, o, **options))
    result = E.evaluate_registered(meshseal.load().model, MeshDataset(dataset, "test"), n_meshes=2, size=64)
    assert result["n_unreadable"] == 2 and result["bit_acc"] == 0.5 and result["registration_success"] == 0.0
    assert result["pose_error_px"] == {"median": None, "p90": None, "max": None}
    json.dumps(result, allow_nan=False)


def test_train_device_errors_are_clear(dataset, tmp_path):
    import yaml

    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(_config(dataset).to_dict()))
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "run"), "--device", "no-such"]) == 2
    if not torch.cuda.is_available():
        assert main(["train", "--config", str(path), "--out", str(tmp_path / "run"), "--device", "cuda"]) == 2


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_camera_known_eval_reads_as_shipped_without_registering(dataset, monkeypatch):
    """`register=False`: every picture is read once, with its true camera, never registered; the report
    holds the camera-known figures alone, and they match the full run's."""
    from meshseal.evaluation import evaluate as E
    from meshseal.data.dataset import MeshDataset

    calls = []
    reading = E._read_or_none
    monkeypatch.setattr(E, "_read_or_none", lambda w, p, o, **options: calls.append(options) or reading(w, p, o, **options))
    model, test = meshseal.load().model, MeshDataset(dataset, "test")
    known = E.evaluate_registered(model, test, n_meshes=1, size=64, register=False)
    assert len(calls) == 1 and all("camera" in c and not c.get("register") for c in calls)
    assert "bit_acc" not in known and "registration_success" not in known
    full = E.evaluate_registered(model, test, n_meshes=1, size=64)
    assert known["bit_acc_known_camera"] == full["bit_acc_known_camera"]
    assert known["tpr_known_camera"] == full["tpr_known_camera"]


def test_eval_reads_every_picture_after_each_attack(dataset, capsys):
    """`meshseal eval --attacks`: each picture read again after each attack, one row an attack; the
    attacks that move the camera need --register; the untouched row reads as the plain reading."""
    assert main(["eval", "--data", str(dataset), "--meshes", "2", "--size", "64", "--attacks", "none,jpeg75",
                 "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(report["attacks"]) == ["none", "jpeg75"]
    assert all(row["pictures"] == 2 and 0.0 <= row["bit_acc"] <= 1.0 for row in report["attacks"].values())
    assert report["attacks"]["none"]["detected"] == report["tpr_known_camera"]
    # The owner who names the message detects every picture the any-message test does, and more.
    assert all(row["named"] >= row["detected"] for row in report["attacks"].values())
    assert report["tpr_message_named"] == report["attacks"]["none"]["named"]
    assert main(["eval", "--data", str(dataset), "--meshes", "1", "--attacks", "resize0.5"]) == 2
    assert "add --register" in capsys.readouterr().err


def test_eval_slices_add_up_to_the_run_over_their_meshes(dataset, capsys):
    """`meshseal eval --start S --meshes N`: a slice of the split, so that slices run in processes of
    their own; slices that cover the meshes merge (`evaluation.merge.merge_results`) into one result
    with every picture counted once and each rate weighted by its pictures. A slice past the split,
    or one without --attacks or --register, is refused in one line."""
    from meshseal.evaluation.merge import merge_results

    def run(*extra):
        assert main(["eval", "--data", str(dataset), "--size", "64", "--attacks", "none,jpeg75", "--json", *extra]) == 0
        return json.loads(capsys.readouterr().out.strip().splitlines()[-1])

    whole = run("--meshes", "2")
    first, second = run("--meshes", "1"), run("--start", "1", "--meshes", "1")
    assert (first["start"], second["start"], first["n_meshes"], second["n_meshes"]) == (0, 1, 1, 1)
    merged = merge_results([first, second])
    assert merged["n_meshes"] == 2 and merged["slices"] == [[0, 1], [1, 1]]
    for name in ("none", "jpeg75"):
        assert merged["attacks"][name]["pictures"] == whole["attacks"][name]["pictures"] == 2
        rates = [part["attacks"][name]["bit_acc"] for part in (first, second)]
        assert merged["attacks"][name]["bit_acc"] == pytest.approx(sum(rates) / 2)
    assert merged["flip_object_p95"] == max(first["flip_object_p95"], second["flip_object_p95"])
    assert merged["flip_object"] == pytest.approx((first["flip_object"] + second["flip_object"]) / 2)
    with pytest.raises(ValueError, match="differ in model"):
        merge_results([first, dict(second, model="other")])
    from meshseal.data.dataset import MeshDataset

    n_test = len(MeshDataset(dataset, "test"))
    assert main(["eval", "--data", str(dataset), "--start", str(n_test), "--attacks", "none"]) == 2
    assert f"has {n_test} meshes" in capsys.readouterr().err
    assert main(["eval", "--data", str(dataset), "--start", "1"]) == 2
    assert "add --register or --attacks" in capsys.readouterr().err


def test_registered_eval_also_reads_each_attacked_picture_with_its_camera(dataset, monkeypatch):
    """Registered, each attacked picture whose frame the attack keeps is also read with its true camera
    (`detected_known_camera`: what registration cost after that attack, and the pose error); untouched, that reading is the
    plain camera-known one; a central crop is read with the crop's own camera (`cropped_camera`); a
    screenshot's canvas, placed at random, has none. (Registration itself is refused here, to keep the
    test short: the camera-known readings are what it is about.)"""
    from meshseal.evaluation import evaluate as E
    from meshseal.data.dataset import MeshDataset

    reading = E._read_or_none
    monkeypatch.setattr(E, "_read_or_none", lambda w, p, o, **options:
                        None if options.get("register") else reading(w, p, o, **options))
    result = E.evaluate_registered(meshseal.load().model, MeshDataset(dataset, "test"), n_meshes=1, size=64,
                                   attacks=["none", "resize0.75", "crop0.8", "screenshot"])
    rows = result["attacks"]
    assert rows["none"]["detected_known_camera"] == result["tpr_known_camera"]
    assert 0.0 <= rows["resize0.75"]["detected_known_camera"] <= 1.0
    assert 0.0 <= rows["crop0.8"]["detected_known_camera"] <= 1.0
    assert "detected_known_camera" not in rows["screenshot"]
    # The pose error where a camera is known: a refused picture is infinitely off (null in JSON).
    assert rows["resize0.75"]["pose_error_px_median"] is None and rows["crop0.8"]["pose_error_px_median"] is None
    assert "pose_error_px_median" not in rows["screenshot"]


def test_an_attacks_pictures_do_not_depend_on_the_others_in_the_list(dataset, monkeypatch):
    """An attack's random draws (the noise) come from its name, not its place in `--attacks`: the
    pictures after `noise2` are the same alone and after another attack."""
    from meshseal.evaluation import evaluate as E
    from meshseal.data.dataset import MeshDataset

    seen = []
    attack = E.attack_picture
    monkeypatch.setattr(E, "attack_picture", lambda name, picture, rng: seen.append((name, out := attack(name, picture, rng)))
                        or out)
    model, test = meshseal.load().model, MeshDataset(dataset, "test")
    for attacks in (["noise2"], ["jpeg75", "noise2"]):
        E.evaluate_registered(model, test, n_meshes=1, size=64, register=False, attacks=attacks)
    noisy = [picture for name, picture in seen if name == "noise2"]
    assert len(noisy) == 2 and np.array_equal(noisy[0], noisy[1])
    assert not np.array_equal(noisy[0], E.attack_picture("noise2", noisy[0], np.random.default_rng(0)))


def test_registered_eval_marks_each_mesh_under_embeds_flip_budget(dataset):
    """Each mesh is marked as `meshseal embed` marks it, within the FLIP budget: a budget out of reach
    lowers every mesh's strength to the floor, which the texture PSNR shows; none marks at strength 1."""
    from meshseal.evaluation import evaluate as E
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.metrics import MIN_STRENGTH

    model, test = meshseal.load().model, MeshDataset(dataset, "test")
    plain = E.evaluate_registered(model, test, n_meshes=2, size=64, register=False, max_flip=None)
    tight = E.evaluate_registered(model, test, n_meshes=2, size=64, register=False, max_flip=1e-4)
    assert "max_flip" not in plain and 39.0 < plain["psnr_texture_shown"] < 41.5
    assert tight["strength_lowered"] == 1.0 and tight["strength_mean"] == MIN_STRENGTH
    assert abs(tight["psnr_texture_shown"] - plain["psnr_texture_shown"] - 20 * math.log10(1 / MIN_STRENGTH)) < 0.5
    assert tight["flip_object"] < plain["flip_object"] and 0.9 < plain["ssim_object"] <= 1.0



def test_bn_renders_measures_the_decoders_statistics_on_rendered_pictures(dataset, tmp_path):
    """train.bn_renders: at the end of a G-buffer run the decoder's batch-norm statistics come from rendered
    pictures of the training meshes; no weight and none of the encoder's statistics change, and the same seed
    gives the same statistics."""
    quiet = lambda *_: None  # noqa: E731
    runs = {}
    for name, pictures in (("baked", 0), ("renders", 3), ("again", 3)):
        Trainer(_texture_config(dataset, steps=1, bn_renders=pictures), tmp_path / name, log=quiet).fit()
        runs[name] = load_file(str(tmp_path / name / "model.safetensors"))
    baked, renders = runs["baked"], runs["renders"]
    statistics = [k for k in baked if k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    decoder = [k for k in statistics if k.startswith("decoder.")]
    assert decoder and any(not torch.allclose(baked[k], renders[k]) for k in decoder)
    for key in baked:
        if key not in decoder:
            assert torch.equal(baked[key], renders[key]), key  # weights and the encoder's statistics
    assert all(torch.equal(runs["again"][k], renders[k]) for k in renders)
