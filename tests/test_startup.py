"""The command line's help and argument errors do not import the heavy libraries (torch, numba, trimesh,
numpy): they are answered from the parser alone, so they come back at once even on a loaded machine.

Run in a fresh interpreter: the test session itself has imported torch long before."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES, BUNNY, README = str(ROOT / "tests" / "fixtures"), str(ROOT / "tests" / "fixtures" / "bunny.glb"), str(ROOT / "README.md")
HEAVY = ("torch", "numba", "trimesh", "numpy", "PIL", "scipy", "galois")

PROBE = """
import contextlib, io, json, sys
from meshseal.cli import build_parser, main
codes = {}
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
    for argv in %r:
        codes[" ".join(argv)] = main(argv)
print(json.dumps({"codes": codes, "loaded": [m for m in %r if m in sys.modules], "stderr": err.getvalue()}))
"""

COMMANDS = [["--help"], ["--version"], ["render", "--help"], ["info", "--help"], ["data", "--help"],
            ["data", "build", "--help"], ["embed", "--help"], ["detect", "--help"], ["eval", "--help"],
            ["models", "--help"]]
BAD_ARGUMENTS = [["bogus"], ["detect"], ["embed", "x.glb"], ["render", "x.glb", "-o", "x.png", "--width", "-3"],
                 ["detect", "x.png", "--workers", "0"],
                 # files that are not there: answered before the model or the mesh is loaded
                 ["detect", "no_such_picture.png", "--mesh", "no_such_mesh.glb"], ["info", "no_such_mesh.obj"],
                 ["embed", "no_such_mesh.glb", "-o", "out.glb", "--message", "ab"],
                 ["render", "no_such_mesh.glb", "-o", "out.png"],
                 ["data", "stats", "no_such_dataset"], ["data", "build", "--from-folder", "no_such_folder", "--out", "o"],
                 ["data", "build", "--textures", "no_such_folder", "--out", "o"],
                 # a model, a format or a value the command would refuse after loading: refused before
                 ["detect", BUNNY, "--mesh", BUNNY, "--model", "no_such_model"],
                 ["embed", BUNNY, "-o", "out.glb", "--message", "ab", "--model", "no_such_model"],
                 ["embed", BUNNY, "-o", "out.glb", "--message", "ab", "--strength", "-1"],
                 ["info", README], ["detect", BUNNY, "--mesh", README],
                 ["eval", "--data", "no_such_dataset"], ["eval", "--data", FIXTURES, "--model", "no_such_model"],
                 ["train", "--config", "no_such_config.yaml"],
                 # what the arguments alone decide: refused before the model and the mesh are loaded
                 ["detect", BUNNY, "--mesh", BUNNY, "--fov", "-3"], ["render", BUNNY, "-o", "out.bmp"],
                 ["embed", BUNNY, "-o", "out.txt", "--message", "ab"],
                 ["embed", BUNNY, "-o", "out.glb", "--message", "ab", "--preview", "out.glb"],
                 ["embed", BUNNY, "-o", "out.glb", "--message", "ab", "--views", "0", "--preview", "sheet.png"],
                 # a message the model cannot carry (its size from the weights file's header)
                 ["embed", BUNNY, "-o", "out.glb", "--message", "toolong"], ["embed", BUNNY, "-o", "out.glb", "--id", str(2 ** 32)],
                 ["detect", BUNNY, "--mesh", BUNNY, "--expect", "toolong"],
                 # attacks: an unknown name, one that moves the camera without --register
                 ["eval", "--data", FIXTURES, "--attacks", "jpeg90,no_such_attack"],
                 ["eval", "--data", FIXTURES, "--attacks", "resize0.5"], ["eval", "--data", FIXTURES, "--start", "3"]]


def probe(argvs):
    out = subprocess.run([sys.executable, "-c", PROBE % (argvs, HEAVY)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_help_does_not_import_the_heavy_libraries():
    result = probe(COMMANDS)
    assert result["loaded"] == []
    assert set(result["codes"].values()) == {0}


def test_bad_arguments_are_refused_without_the_heavy_libraries(tmp_path):
    empty = tmp_path / "no_pictures_here"
    empty.mkdir()
    result = probe(BAD_ARGUMENTS + [["detect", str(empty), "--mesh", BUNNY]])
    assert result["loaded"] == []
    assert set(result["codes"].values()) == {2}
    assert result["stderr"].count("meshseal: error:") == len(BAD_ARGUMENTS) + 1
    assert "no pictures in this folder" in result["stderr"] and "out.bmp: the output must be a .png" in result["stderr"]
    assert "out.txt: unsupported mesh format" in result["stderr"] and "--fov must be between" in result["stderr"]
    assert result["stderr"].count("text message is 7 bytes in UTF-8; a 64-bit model carries at most 4") == 2
    assert "ID must be an integer from 0 to 4294967295" in result["stderr"]
    assert "unknown attack(s) no_such_attack" in result["stderr"] and "change the picture's camera" in result["stderr"]
    assert "no_such_mesh.glb: no such mesh file" in result["stderr"]
    assert "unknown model 'no_such_model'" in result["stderr"] and "README.md: unsupported mesh format" in result["stderr"]
    assert "--start slices the pictures read as `detect` reads them: add --register or --attacks" in result["stderr"]


def test_a_models_size_is_read_from_its_weights_header_without_torch(tmp_path):
    from meshseal.shipped import model_bits

    assert model_bits(None) == 64 and model_bits("learned32") == 32
    (tmp_path / "other.safetensors").write_bytes(b"not a weights file")
    assert model_bits(str(tmp_path / "other.safetensors")) is None


def test_a_file_that_is_no_picture_is_refused_before_torch(tmp_path):
    """A text file or an empty file named as the picture: its one-line error from the file's header (PIL
    alone), not after torch and the model are loaded."""
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    result = probe([["detect", README, "--mesh", BUNNY], ["detect", str(empty), "--mesh", BUNNY]])
    assert [m for m in result["loaded"] if m != "PIL"] == []
    assert set(result["codes"].values()) == {2}
    assert "README.md: not a readable image (not an image format PIL reads)" in result["stderr"]
    assert "empty.png: image file is empty" in result["stderr"]


SUBMODULE_FIRST = """
import importlib, types
for package, name in %r:
    importlib.import_module(package + "." + name)  # the submodule first: the import system records it
    value = getattr(importlib.import_module(package), name)
    assert callable(value) and not isinstance(value, types.ModuleType), (package, name, value)
    assert name in dir(importlib.import_module(package))
print("ok")
"""


def test_lazy_names_stay_the_functions_after_their_submodule_is_imported():
    """`meshseal.render.interpolate` is the function and `meshseal.data.build` the builder, as when the
    packages imported everything at once, even where the submodule of the same name was imported first."""
    pairs = [("meshseal.render", "interpolate"), ("meshseal.render", "unrender"), ("meshseal.data", "build")]
    out = subprocess.run([sys.executable, "-c", SUBMODULE_FIRST % (pairs,)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    from meshseal import Watermarker, load_mesh
    from meshseal.render import MeshRenderer, make_renderer

    assert callable(load_mesh) and isinstance(Watermarker, type) and isinstance(MeshRenderer, type)
    assert callable(make_renderer)


READ_PATH = """
import json, sys
import meshseal.api, meshseal.methods.charts
from meshseal import payload
soft = [2.0 * bit - 1.0 for bit in %r]  # encode's bits, made outside: encoding uses galois
print(json.dumps({"message": payload.decode(soft, key="k").message,
                  "loaded": [m for m in %r if m in sys.modules]}))
"""


def test_reading_a_clean_codeword_does_not_import_what_detect_does_not_use():
    """The reading path (the API, the charts module, decoding a word that is already a codeword) leaves
    galois, matplotlib and scipy.ndimage unimported: each would add its import to every `meshseal detect`."""
    from meshseal.payload import encode

    bits = encode("ab42", key="k").tolist()
    out = subprocess.run([sys.executable, "-c", READ_PATH % (bits, ("galois", "matplotlib", "scipy.ndimage"))],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result == {"message": "ab42", "loaded": []}
