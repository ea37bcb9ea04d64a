"""Text in, text out through the command line with the shipped model: keys, wrong keys, unmarked
pictures, a known message (--expect), pooling, folders and per-picture errors."""

import json
from pathlib import Path

import numpy as np
import pytest

from meshseal.cli import main

FIXTURES = Path(__file__).parent / "fixtures"
BUNNY = str(FIXTURES / "bunny.glb")


@pytest.fixture(scope="module")
def pictures(tmp_path_factory):
    """Two views of the bunny marked with 'ab42' under key 's3cret', and one of the unmarked bunny."""
    folder = tmp_path_factory.mktemp("pictures")
    assert main(["embed", BUNNY, "-o", str(folder / "m.glb"), "--message", "ab42", "--key", "s3cret", "--views", "1"]) == 0
    assert main(["render", str(folder / "m.glb"), "-o", str(folder / "views" / "v.png"), "--views", "2", "--seed", "3",
                 "--width", "192", "--height", "192"]) == 0
    assert main(["render", BUNNY, "-o", str(folder / "clean.png"), "--width", "192", "--height", "192"]) == 0
    return folder


def _detect(capsys, *argv):
    capsys.readouterr()
    code = main(["detect", *map(str, argv), "--mesh", BUNNY, "--json"])
    captured = capsys.readouterr()
    return code, [json.loads(line) for line in captured.out.splitlines()], captured.err


def test_the_right_key_reads_the_text_and_nothing_else_does(pictures, capsys, monkeypatch):
    code, results, _ = _detect(capsys, pictures / "views", pictures / "clean.png", "--key", "s3cret")
    assert code == 0 and len(results) == 3
    marked, clean = results[:2], results[2]
    for result in marked:
        assert result["detected"] and result["message"] == "ab42" and result["p_value"] < 1e-6
        assert result["camera"] == "metadata" and result["errors_corrected"] is not None
    assert not clean["detected"] and clean["message"] is None and clean["p_value"] > 1e-3
    # Another key, or none (the public key): the mark is noise, and no reason is given (a mark under
    # another key is not told apart from no mark); without a key a note says what was assumed.
    for key in (["--key", "other"], []):
        code, results, err = _detect(capsys, pictures / "views" / "v_0.png", *key)
        assert code == 1 and not results[0]["detected"] and results[0]["message"] is None
        assert "reason" not in results[0] and results[0]["silhouette_iou"] > 0.9
        assert ("public key" in err) == (not key)
    # The key from the environment, as a known message; another message is refused but named.
    monkeypatch.setenv("MESHSEAL_KEY", "s3cret")
    code, results, _ = _detect(capsys, pictures / "views" / "v_1.png", "--expect", "ab42")
    assert results[0]["detected"] and results[0]["p_value"] < 1e-6
    code, results, _ = _detect(capsys, pictures / "views" / "v_1.png", "--expect", "ab43")
    # The default's pilot finds the mark; the match does not name ab43 and the code reads ab42: exit 1.
    assert code == 1 and results[0]["detected"] and results[0]["named"] is False and results[0]["message"] == "ab42"
    assert main(["detect", str(pictures / "views" / "v_1.png"), "--mesh", BUNNY, "--expect", "ab43"]) == 1
    assert "the match does not name \"ab43\": the code reads \"ab42\"" in capsys.readouterr().out


def test_pooling_decides_once_and_bad_pictures_do_not_stop_the_batch(pictures, capsys):
    code, results, _ = _detect(capsys, pictures / "views", "--key", "s3cret", "--pool")
    assert code == 0 and len(results) == 1
    assert results[0]["detected"] and results[0]["message"] == "ab42" and results[0]["pictures"] == 2
    code, results, err = _detect(capsys, pictures / "missing.png", pictures / "views" / "v_0.png", "--key", "s3cret")
    assert code == 2 and err.count("meshseal: error:") == 1 and "missing.png" in err
    assert "error" in results[0] and results[1]["message"] == "ab42"


@pytest.mark.heavy
def test_worker_processes_read_as_one_process_does(pictures, capsys, monkeypatch):
    """--workers 2: spawned processes read the pictures; the lines, their order, the errors and the
    pooled decision are those of one process."""
    pictures_named = [pictures / "missing.png", pictures / "views", pictures / "clean.png", "--key", "s3cret"]
    alone = _detect(capsys, *pictures_named, "--workers", "1")
    together = _detect(capsys, *pictures_named, "--workers", "2")
    assert alone[0] == together[0] == 2 and len(alone[1]) == len(together[1]) == 4
    assert all(_same_reading(a, b) for a, b in zip(alone[1], together[1]))
    assert together[2].count("meshseal: error:") == 1 and "missing.png" in together[2]
    assert [r.get("message") for r in together[1]] == [None, "ab42", "ab42", None]
    pooled = _detect(capsys, pictures / "views", "--key", "s3cret", "--pool", "--workers", "2")
    assert _same_reading(pooled[1][0], _detect(capsys, pictures / "views", "--key", "s3cret", "--pool")[1][0])
    # Without --workers, this process reads until a pool pays (here: from the third picture on).
    import meshseal.commands.model as model

    monkeypatch.setattr(model, "pool_pays", lambda seconds, remaining, cores, start_cost: len(seconds) >= 2)
    switched = _detect(capsys, *pictures_named)
    assert switched[0] == 2 and all(_same_reading(a, b) for a, b in zip(alone[1], switched[1]))
    assert len(switched[1]) == 4 and switched[2].count("meshseal: error:") == 1


def test_a_pool_starts_once_the_pictures_left_would_be_read_sooner_by_it():
    """`pool_pays`: judged on the pace of the last picture read here (the first pays one-time costs that
    each worker pays again), against the seconds a worker takes to start."""
    from meshseal.commands.model import pool_pays

    assert not pool_pays([0.5], 1000, 2, 3.0)  # one picture read: no pace yet
    assert not pool_pays([0.5, 0.04], 100, 2, 3.0)  # camera known: 2 s of work left, a worker takes 3.5
    assert pool_pays([0.5, 0.04], 300, 2, 3.0)  # ... 6 s left, read in half
    assert pool_pays([2.0, 1.5], 6, 2, 3.0) and not pool_pays([2.0, 1.5], 4, 2, 3.0)  # registered pictures
    assert not pool_pays([2.0, 1.5], 100, 1, 3.0)  # one core: nothing to share


def _same_reading(a: dict, b: dict) -> bool:
    """The same result line up to float rounding: a worker runs one thread, the caller several, and
    sums in another order move a z-score in its third decimal."""
    rounded = ("soft", "p_value")
    if {k: v for k, v in a.items() if k not in rounded} != {k: v for k, v in b.items() if k not in rounded}:
        return False
    if "soft" in a and not np.allclose(a["soft"], b["soft"], atol=5e-3):
        return False
    return a.get("p_value") is None or np.isclose(np.log(a["p_value"]), np.log(b["p_value"]), rtol=1e-3)


def test_payload_limits_and_models_listing(pictures, tmp_path, capsys):
    for argv in (["--message", "too long"], ["--id", str(2 ** 32)], ["--message", "ab", "--key", ""]):
        capsys.readouterr()
        assert main(["embed", BUNNY, "-o", str(tmp_path / "x.glb"), *argv]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("meshseal: error:"), (argv, err)
    assert not (tmp_path / "x.glb").exists()
    capsys.readouterr()
    assert main(["models", "--json"]) == 0
    models = {m["name"]: m for m in json.loads(capsys.readouterr().out)}
    assert models["default"]["payload_bits"] >= 32 and models["default"]["calibrated"]
    assert models["default"]["informed"] and models["learned32"]["payload_bits"] == 12


def test_detect_says_why_where_a_plausible_mistake_explains_no_mark(pictures, capsys):
    """The marked mesh given as the original, or another mesh: 'not detected' says why, exit 1."""
    capsys.readouterr()
    picture = pictures / "views" / "v_0.png"
    code = main(["detect", str(picture), "--mesh", str(pictures / "m.glb"), "--key", "s3cret"])
    out = capsys.readouterr().out
    assert code == 1 and "not detected" in out and "itself marked under this key" in out, out
    code = main(["detect", str(picture), "--mesh", str(FIXTURES / "suzanne.glb"), "--key", "s3cret", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 1 and not result["detected"] and result["silhouette_iou"] < 0.8
    assert result["reason"].startswith("the picture does not seem to show this mesh"), result
    # The right mesh under the right key: no reason, exit 0.
    code = main(["detect", str(picture), "--mesh", BUNNY, "--key", "s3cret", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 0 and result["detected"] and "reason" not in result


def test_a_mark_of_the_previous_default_is_named_where_the_default_reads_none(pictures, tmp_path, capsys):
    """A mark made by `fine` (the default before 64^2 cells): the default says so and which model reads it; the
    clean picture gets no such note."""
    assert main(["embed", BUNNY, "-o", str(tmp_path / "f.glb"), "--model", "fine", "--message", "ab42", "--views", "0"]) == 0
    assert main(["render", str(tmp_path / "f.glb"), "-o", str(tmp_path / "f.png"), "--seed", "3",
                 "--width", "192", "--height", "192"]) == 0
    code, (result, clean), _ = _detect(capsys, tmp_path / "f.png", pictures / "clean.png")
    assert code == 1 and not result["detected"] and result["p_value"] > 1e-3
    assert "--model fine" in result["reason"] and "'ab42'" in result["reason"], result
    assert not clean["detected"] and "reason" not in clean, clean


def test_own_mark_is_read_from_the_texture_alone_under_its_key_only(pictures):
    import meshseal
    from meshseal.payload import FPR

    wm = meshseal.load()
    marked, clean = wm.original(pictures / "m.glb"), wm.original(BUNNY)
    assert wm.method.own_mark_pvalue(marked, "s3cret") < FPR
    for original, key in ((marked, "other"), (marked, None), (clean, "s3cret"), (clean, None)):
        assert wm.method.own_mark_pvalue(original, key) > 1e-3, key


def test_detect_exit_status():
    from meshseal.commands.model import detect_status

    assert detect_status(0, [True, False]) == 0  # any picture detected
    assert detect_status(0, [False, False]) == 1  # none
    assert detect_status(0, [None]) == 0  # no decision (raw bits of an uncalibrated model)
    assert detect_status(1, [True]) == 2  # a picture could not be read


def test_a_mark_in_an_obj_jpeg_texture_survives_the_file(tmp_path, capsys):
    """crate.obj's texture is a JPEG: the marked OBJ keeps it a JPEG (quality 95, 4:4:4), and a
    picture of the file as written reads the mark."""
    crate = FIXTURES / "sh3d_crate" / "crate.obj"
    assert main(["embed", str(crate), "-o", str(tmp_path / "crate_marked.obj"), "--message", "jp", "--views", "1"]) == 0
    assert (tmp_path / "crate_marked.jpg").is_file()
    assert main(["render", str(tmp_path / "crate_marked.obj"), "-o", str(tmp_path / "v.png"), "--width", "192",
                 "--height", "192", "--camera", "1.5,-2.5,2"]) == 0
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "v.png"), "--mesh", str(crate), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["detected"] and result["message"] == "jp"


def _cells(method, bits, mu, key, rng):
    """A reading whose cell sums carry `bits` at `mu` per message cell (the pilot's at its gain) in unit Gaussian noise."""
    import types

    import torch

    encoder = method.encoder
    assign, sign = encoder.pattern(method.key_seed(key), encoder.chips)
    signs = torch.cat([2 * bits - 1, torch.ones(1)])  # index n_bits: the pilot's cells, where the model has one
    gain = torch.where(assign == method.n_bits, encoder.pilot_gain, 1.0)  # the pilot's amplitude, as `cells` lays it
    cell = sign * signs[assign] * gain * mu + torch.from_numpy(rng.standard_normal(assign.numel())).float()
    return types.SimpleNamespace(evidence=cell, tries=1, box=None, camera="metadata", registration_iou=None)


def test_a_list_of_ids_names_the_one_carried_pays_for_its_length_and_is_never_too_bold():
    from meshseal import payload
    from meshseal.api import load

    method = load("dense").method  # every cell carries the message (the default's pilot finds such marks: below)
    ids = tuple(range(5000, 6000))
    assert np.array_equal(payload.encode_many(ids[:50] + ("ab42",), "k").numpy(),
                          np.stack([payload.encode(m, "k").numpy() for m in ids[:50] + ("ab42",)]))
    rng = np.random.default_rng(0)
    carried = payload.encode(5123, "k")
    # Faint: the any-message test and the code miss it; the list finds it, its p-value times 1000 and all.
    faint = _cells(method, carried, 0.11, "k", rng)
    alone, listed = method.decide([faint], "k"), method.decide([faint], "k", ids)
    assert not alone.detected and listed.detected and listed.message == 5123 and listed.list_only
    one = method.decide([faint], "k", 5123)
    assert listed.p_value == pytest.approx(min(1.0, len(ids) * one.p_value), rel=1e-9)
    # Clear, but not on the list: the code reads the mark's own ID and the list is not credited.
    clear = _cells(method, carried, 0.3, "k", rng)
    elsewhere = method.decide([clear], "k", tuple(range(6000, 7000)))
    assert not elsewhere.detected and elsewhere.message == 5123 and elsewhere.list_only is None
    assert method.decide([clear], "k", ids).list_only is False
    # No mark: the list's p-values are conservative (no more small ones than their level allows).
    p = np.array([method.decide([_cells(method, carried, 0.0, "k", rng)], "k", ids).p_value for _ in range(300)])
    assert (p <= 0.05).mean() <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 300) and p.min() > 1e-4
    # The default's pilot (half the cells, the key's own signs) finds faint marks whatever their message,
    # most of them too faint for the code to read; the list still names them, on the message's own cells.
    default = load("default").method
    found, unread, named = 0, 0, 0
    for _ in range(20):
        faint = _cells(default, carried, 0.18, "k", rng)
        alone, listed = default.decide([faint], "k"), default.decide([faint], "k", ids)
        found += bool(alone.detected and default.pilot_pvalue(faint.evidence[None], "k") < 1e-6)
        unread += alone.message is None
        named += bool(listed.detected and listed.message == 5123)
    assert found >= 19 and unread >= 14 and named >= 18, (found, unread, named)


def test_detect_reads_a_list_of_ids_from_a_file(pictures, capsys, tmp_path):
    listing = tmp_path / "ids.txt"
    listing.write_text("# our buyers\n12\n\n7  # repeated below\n7\n")
    code, results, _ = _detect(capsys, pictures / "views" / "v_0.png", "--key", "s3cret", "--expect-ids", listing)
    # a text mark, not an ID listed: the default's pilot finds the mark, the list names none of it
    assert code == 1 and results[0]["named"] is False and results[0]["message"] == "ab42"
    listing.write_text("12\nseven\n")
    assert main(["detect", str(pictures / "clean.png"), "--mesh", BUNNY, "--expect-ids", str(listing)]) == 2
    assert "line 2" in capsys.readouterr().err
