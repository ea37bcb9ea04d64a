#!/usr/bin/env python
"""Regenerate the small test fixtures under tests/fixtures/ from package registries.

Sources (all CC0 / BSD, see tests/fixtures/LICENSES, which this script rewrites):
  * npm   ``@pmndrs/assets``          (``npm pack``)         -> bunny.glb, suzanne.glb, bunny.ply
  * Debian ``sweethome3d-furniture``  (``apt-get download``) -> sh3d_crate/, sh3d_deckChair/,
                                                                multi_material.glb
  * PyPI  ``panda3d`` wheel           (``pip download``)     -> teapot/ (geometry of models/teapot.egg.pz)
  * PyPI  ``scikit-image`` (installed) skimage.data brick/grass/gravel -> textures/*.png and the
    textures put on the meshes that come without one.
  * generated here: cube.off, tetra.stl

Needs: npm, apt-get + dpkg-deb (run ``apt-get update`` once first), and in the Python env
numpy, pillow, trimesh, scikit-image, fast-simplification, DracoPy (``pip install DracoPy``).

Usage:  python tools/make_fixtures.py [--out tests/fixtures] [--work DIR] [--keep]

Output is deterministic for given package versions (versions are pinned below; if a pinned
version is gone from a registry the script falls back to the current one and says so).
"""

from __future__ import annotations

import argparse
import base64
import glob
import json
import os
import shutil
import struct
import subprocess
import sys
import tarfile
import tempfile
import zipfile
import zlib

import numpy as np
from PIL import Image

NPM_PKG, NPM_VER = "@pmndrs/assets", "1.7.0"
DEB_PKG, DEB_VER = "sweethome3d-furniture", "1.8-1"
PYPI_PKG, PYPI_VER = "panda3d", "1.10.16"

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SH3D_CATALOG = "usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f"

# Grayscale skimage textures are tinted to RGB (dark colour, bright colour) so every channel varies.
TINTS = {
    "brick": ((0.22, 0.07, 0.04), (1.00, 0.72, 0.55)),
    "grass": ((0.04, 0.14, 0.02), (0.70, 0.98, 0.42)),
    "gravel": ((0.10, 0.09, 0.08), (0.96, 0.90, 0.80)),
}

# Sweet Home 3D models looked at and what was decided (written to LICENSES).
SH3D_REJECTED = [
    ("BlendSwap-CC-BY.sh3f, KatorLegaz.sh3f, Reallusion.sh3f, Scopia.sh3f (all models)",
     "CC-BY-3.0 catalogs (debian/copyright): not allowed"),
    ("BlendSwap-CC-0 basketball", "CC0 (SEspider) but its .mtl names 'BasketBall-By-RichardT.WhiteJr.blend': "
     "authorship unclear, skipped"),
    ("BlendSwap-CC-0 barrel", "CC0 (GyngaNynja), 2 textures; fine, but deckChair is smaller and also has an "
     "untextured material"),
    ("BlendSwap-CC-0 woodToy, drawersCabinet, lowerCabinet, cardGame, tatami",
     "CC0 multi-texture candidates; larger or less varied than deckChair, not needed"),
    ("BlendSwap-CC-0 stoneLantern, rock1, JapaneseLantern", "CC0 single-texture candidates; crate chosen instead"),
    ("BlendSwap-CC-0 bed1, bed2, textMarker, technicalTable1/2", "no UVs (no vt lines)"),
    ("BlendSwap-CC-0 bedWithTexture, poolTable, kitchenaid, couch, ...", "too large (> 20k faces / > 1 MB)"),
]


def log(*a):
    print("[make_fixtures]", *a, file=sys.stderr, flush=True)


def run(cmd, cwd=None):
    log("$", " ".join(cmd))
    return subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, text=True).stdout


# --------------------------------------------------------------------------- fetching
def fetch_npm(work):
    d = os.path.join(work, "npm")
    os.makedirs(d, exist_ok=True)
    try:
        out = run(["npm", "pack", f"{NPM_PKG}@{NPM_VER}", "--pack-destination", d], cwd=d)
    except subprocess.CalledProcessError:
        log(f"WARNING: {NPM_PKG}@{NPM_VER} not available, using latest")
        out = run(["npm", "pack", NPM_PKG, "--pack-destination", d], cwd=d)
    tgz = os.path.join(d, out.strip().splitlines()[-1])
    with tarfile.open(tgz) as tf:
        pkg = json.load(tf.extractfile("package/package.json"))
        models = {}
        for name in ("bunny", "suzi"):
            js = tf.extractfile(f"package/models/{name}.glb.js").read().decode()
            models[name] = base64.b64decode(js.split("base64,", 1)[1].split("'", 1)[0].split('"', 1)[0])
    return pkg["version"], pkg.get("license", "?"), models


def fetch_deb(work):
    d = os.path.join(work, "deb")
    os.makedirs(d, exist_ok=True)
    try:
        run(["apt-get", "download", f"{DEB_PKG}={DEB_VER}"], cwd=d)
    except subprocess.CalledProcessError:
        log(f"WARNING: {DEB_PKG}={DEB_VER} not available, using the candidate version")
        run(["apt-get", "download", DEB_PKG], cwd=d)
    deb = sorted(glob.glob(os.path.join(d, f"{DEB_PKG}_*.deb")))[-1]
    version = run(["dpkg-deb", "-f", deb, "Version"]).strip()
    root = os.path.join(d, "x")
    run(["dpkg-deb", "-x", deb, root])
    cat_dir = os.path.join(d, "BlendSwap-CC-0")
    with zipfile.ZipFile(os.path.join(root, SH3D_CATALOG)) as z:
        props = z.read("PluginFurnitureCatalog.properties").decode("latin-1")
        for m in z.namelist():
            if m.startswith(("blendswap-cc-0/crate/", "blendswap-cc-0/deckChair/")) or m == "LICENSE.TXT":
                z.extract(m, cat_dir)
    return version, cat_dir, props


def fetch_pypi(work):
    d = os.path.join(work, "pypi")
    os.makedirs(d, exist_ok=True)
    base = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
            "--platform", "manylinux2014_x86_64", "--python-version", "3.11", "-d", d]
    try:
        run(base + [f"{PYPI_PKG}=={PYPI_VER}"])
    except subprocess.CalledProcessError:
        log(f"WARNING: {PYPI_PKG}=={PYPI_VER} not available, using latest")
        run(base + [PYPI_PKG])
    whl = sorted(glob.glob(os.path.join(d, f"{PYPI_PKG}-*.whl")))[-1]
    version = os.path.basename(whl).split("-")[1]
    with zipfile.ZipFile(whl) as z:
        egg = zlib.decompress(z.read("panda3d/models/teapot.egg.pz"), 47).decode()
    return version, egg


# --------------------------------------------------------------------------- helpers
def texture(name, size):
    import skimage.data

    g = getattr(skimage.data, name)().astype(np.float64) / 255.0
    lo, hi = (np.array(c) for c in TINTS[name])
    rgb = lo + g[..., None] * (hi - lo)
    img = Image.fromarray(np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8), "RGB")
    return img.resize((size, size), Image.LANCZOS)


def decode_draco_glb(data):
    """Return (vertices, faces) of the single Draco-compressed primitive of a GLB."""
    import DracoPy

    jlen = struct.unpack("<I", data[12:16])[0]
    gltf = json.loads(data[20:20 + jlen])
    off = 20 + jlen
    blen = struct.unpack("<I", data[off:off + 4])[0]
    binchunk = data[off + 8:off + 8 + blen]
    prim = gltf["meshes"][0]["primitives"][0]
    bv = gltf["bufferViews"][prim["extensions"]["KHR_draco_mesh_compression"]["bufferView"]]
    start = bv.get("byteOffset", 0)
    m = DracoPy.decode(binchunk[start:start + bv["byteLength"]])
    return np.asarray(m.points, np.float64).reshape(-1, 3), np.asarray(m.faces, np.int64).reshape(-1, 3)


def simplify(v, f, target_faces):
    import fast_simplification
    import trimesh

    if len(f) > target_faces:
        v, f = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32),
                                            target_reduction=1.0 - target_faces / len(f))
    m = trimesh.Trimesh(v, f, process=True)  # merge / drop degenerate
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def spherical_corner_uv(pos, faces, center, up=1):
    """Per-corner spherical UVs (F, k, 2) around `center` with Y (up=1) as the pole axis.

    Faces that straddle the u seam get u + 1 on their small-u corners (REPEAT wrapping makes
    that correct), so no triangle smears the whole texture.
    """
    p = pos - center
    ax = [i for i in range(3) if i != up]
    r = np.linalg.norm(p, axis=1) + 1e-12
    u = (np.arctan2(p[:, ax[0]], p[:, ax[1]]) / (2 * np.pi)) % 1.0
    v = 1.0 - np.arccos(np.clip(p[:, up] / r, -1, 1)) / np.pi
    cu, cv = u[faces], v[faces]
    span = cu.max(1) - cu.min(1)
    wrap = span > 0.5
    cu[wrap] = np.where(cu[wrap] < 0.5, cu[wrap] + 1.0, cu[wrap])
    return np.stack([cu, cv], -1)


def split_by_corner_uv(v, n, f, cuv):
    """Unweld vertices so each (vertex, uv) pair is unique -> per-vertex uv for glTF."""
    key = np.concatenate([f.reshape(-1, 1).astype(np.float64), np.round(cuv.reshape(-1, 2), 6)], 1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    vid = uniq[:, 0].astype(np.int64)
    return v[vid], n[vid], uniq[:, 1:], inv.reshape(f.shape)


def textured_trimesh(v, f, tex_img, mat_name):
    import trimesh

    n = trimesh.Trimesh(v, f, process=False).vertex_normals
    c = 0.5 * (v.min(0) + v.max(0))
    cuv = spherical_corner_uv(v, f, c, up=1)
    v2, n2, uv, f2 = split_by_corner_uv(v, n, f, cuv)
    mat = trimesh.visual.material.PBRMaterial(
        name=mat_name, baseColorTexture=tex_img, baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0, roughnessFactor=0.8)
    return trimesh.Trimesh(v2, f2, vertex_normals=n2, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=mat))


def export_glb(path, named_meshes, root=None):
    import trimesh

    scene = trimesh.Scene()
    parent = None
    if root is not None:
        name, matrix = root
        scene.graph.update(frame_to=name, frame_from=scene.graph.base_frame, matrix=matrix)
        parent = name
    for name, mesh in named_meshes:
        scene.add_geometry(mesh, geom_name=name, node_name=name, parent_node_name=parent)
    with open(path, "wb") as fh:
        fh.write(scene.export(file_type="glb"))


def y_up_to_z_up(v):
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)


# --------------------------------------------------------------------------- egg -> obj
def parse_egg(text):
    """Minimal parser for panda3d's teapot.egg: returns [(group, verts, normals, polys)]."""
    toks = text.replace("{", " { ").replace("}", " } ").split()
    i = 0
    pools, polys, order = {}, [], []

    def skip_block(i):  # toks[i] == '{'
        depth = 0
        while True:
            if toks[i] == "{":
                depth += 1
            elif toks[i] == "}":
                depth -= 1
                if depth == 0:
                    return i + 1
            i += 1

    while i < len(toks):
        t = toks[i]
        if t == "<VertexPool>":
            name = toks[i + 1]
            i += 3
            pv, pn = {}, {}
            while toks[i] != "}":
                assert toks[i] == "<Vertex>", toks[i]
                idx = int(toks[i + 1])
                pv[idx] = [float(x) for x in toks[i + 3:i + 6]]
                i += 6
                while toks[i] != "}":
                    if toks[i] == "<Normal>":
                        pn[idx] = [float(x) for x in toks[i + 2:i + 5]]
                        i += 6
                    else:
                        i = skip_block(i + 1)
                i += 1
            i += 1
            pools[name] = (pv, pn)
            order.append(name)
        elif t == "<VertexRef>":
            j = i + 2
            idx = []
            while toks[j] != "<Ref>":
                idx.append(int(toks[j]))
                j += 1
            polys.append((toks[j + 2], idx))
            i = j + 5
        else:
            i += 1
    out = []
    for name in order:
        pv, pn = pools[name]
        ids = sorted(pv)
        remap = {k: n for n, k in enumerate(ids)}
        V = np.array([pv[k] for k in ids])
        N = np.array([pn.get(k, [0, 0, 0]) for k in ids])
        P = [[remap[k] for k in idx] for pool, idx in polys if pool == name]
        out.append((name, V, N, P))
    return out


def write_teapot(out_dir, egg, tex_img):
    parts = parse_egg(egg)
    allv = np.concatenate([p[1] for p in parts])
    center = 0.5 * (allv.min(0) + allv.max(0))
    os.makedirs(out_dir, exist_ok=True)
    lines = ["# Utah teapot (M. Newell, 1975) from panda3d's models/teapot.egg.pz,",
             "# spherical UVs added by tools/make_fixtures.py. Y-up.", "mtllib teapot.mtl"]
    vt_index, vt_lines = {}, []
    body = []
    voff = 0
    nquads = ntris = 0
    for name, V, N, P in parts:
        body.append(f"o {name}")
        body += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
        body += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in N]
        body.append("usemtl teapot")
        body.append("s 1")
        for poly in P:
            cuv = spherical_corner_uv(V, np.array([poly]), center, up=1)[0]
            corners = []
            for k, (u, v) in zip(poly, cuv):
                key = (round(float(u), 5), round(float(v), 5))
                if key not in vt_index:
                    vt_index[key] = len(vt_index) + 1
                    vt_lines.append(f"vt {key[0]:.5f} {key[1]:.5f}")
                corners.append(f"{k + 1 + voff}/{vt_index[key]}/{k + 1 + voff}")
            body.append("f " + " ".join(corners))
            nquads += len(poly) == 4
            ntris += len(poly) == 3
        voff += len(V)
    with open(os.path.join(out_dir, "teapot.obj"), "w") as fh:
        fh.write("\n".join(lines + vt_lines + body) + "\n")
    with open(os.path.join(out_dir, "teapot.mtl"), "w") as fh:
        fh.write("# teapot material (tools/make_fixtures.py)\nnewmtl teapot\nNs 32\nKa 1 1 1\nKd 1 1 1\n"
                 "Ks 0 0 0\nd 1\nillum 2\nmap_Kd teapot.jpg\n")
    tex_img.save(os.path.join(out_dir, "teapot.jpg"), quality=90)


# --------------------------------------------------------------------------- main
def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "fixtures"))
    ap.add_argument("--work", default=None, help="download/extract dir (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the work dir")
    args = ap.parse_args()

    import skimage
    import trimesh

    work = args.work or tempfile.mkdtemp(prefix="meshseal_fixtures_")
    os.makedirs(work, exist_ok=True)
    out = args.out
    os.makedirs(out, exist_ok=True)
    try:
        npm_ver, npm_lic, models = fetch_npm(work)
        deb_ver, cat_dir, props = fetch_deb(work)
        pypi_ver, egg = fetch_pypi(work)

        # textures --------------------------------------------------------------
        os.makedirs(os.path.join(out, "textures"), exist_ok=True)
        for name in TINTS:
            texture(name, 128).save(os.path.join(out, "textures", f"{name}.png"), optimize=True)

        # bunny / suzanne ---------------------------------------------------------
        bv, bf = simplify(*decode_draco_glb(models["bunny"]), 4000)
        export_glb(os.path.join(out, "bunny.glb"),
                   [("bunny", textured_trimesh(bv, bf, texture("grass", 256), "bunny_grass"))])
        sv, sf = simplify(*decode_draco_glb(models["suzi"]), 4000)
        export_glb(os.path.join(out, "suzanne.glb"),
                   [("suzanne", textured_trimesh(sv, sf, texture("gravel", 256), "suzanne_gravel"))])

        # bunny.ply (Z-up, ~2k faces, vertex colours) ------------------------------
        pv, pf = simplify(*decode_draco_glb(models["bunny"]), 2000)
        pv = y_up_to_z_up(pv)
        t = (pv - pv.min(0)) / np.ptp(pv, 0)
        cols = np.concatenate([(40 + 215 * t).astype(np.uint8), np.full((len(pv), 1), 255, np.uint8)], 1)
        ply = trimesh.Trimesh(pv, pf, vertex_colors=cols, process=False)
        with open(os.path.join(out, "bunny.ply"), "wb") as fh:
            fh.write(ply.export(file_type="ply", encoding="binary"))

        # cube.off (quads, no uvs) and tetra.stl ------------------------------------
        cube_v = [(x, y, z) for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]
        cube_q = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
        with open(os.path.join(out, "cube.off"), "w") as fh:
            fh.write("OFF\n# unit cube, quad faces, Z-up (tools/make_fixtures.py)\n8 6 0\n")
            fh.writelines(f"{x} {y} {z}\n" for x, y, z in cube_v)
            fh.writelines("4 " + " ".join(map(str, q)) + "\n" for q in cube_q)
        tv = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
        tf = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
        with open(os.path.join(out, "tetra.stl"), "wb") as fh:
            fh.write(trimesh.Trimesh(tv, tf, process=False).export(file_type="stl"))

        # teapot (OBJ + MTL + JPEG) -------------------------------------------------
        write_teapot(os.path.join(out, "teapot"), egg, texture("brick", 256))

        # Sweet Home 3D models ------------------------------------------------------
        src = os.path.join(cat_dir, "blendswap-cc-0")
        d = os.path.join(out, "sh3d_crate")
        os.makedirs(d, exist_ok=True)
        for f in ("crate.obj", "crate.mtl"):
            shutil.copyfile(os.path.join(src, "crate", f), os.path.join(d, f))
        Image.open(os.path.join(src, "crate", "crate.jpg")).convert("RGB").resize(
            (256, 256), Image.LANCZOS).save(os.path.join(d, "crate.jpg"), quality=90)
        shutil.copyfile(glob.glob(os.path.join(src, "crate", "*License.html"))[0],
                        os.path.join(d, "BLENDSWAP_LICENSE.html"))
        d = os.path.join(out, "sh3d_deckChair")
        os.makedirs(d, exist_ok=True)
        for f in ("deckChair.obj", "deckChair.mtl", "BEuropean_Beech.jpg", "BlueWhite_Stripes.jpg",
                  "BLENDSWAP_LICENSE.txt"):
            shutil.copyfile(os.path.join(src, "deckChair", f), os.path.join(d, f))

        # multi_material.glb: the deck chair as 3 named nodes under a scaled root ----
        sc = trimesh.load(os.path.join(d, "deckChair.obj"), force="scene", group_material=True)
        rename = {"ChairFrame": "frame", "Chair_Fabric": "fabric", "Metal": "metal"}
        parts = []
        for g in sc.geometry.values():
            src_mat = g.visual.material
            name = rename.get(src_mat.name, src_mat.name)
            pbr = src_mat.to_pbr()  # keeps Kd as baseColorFactor and map_Kd as baseColorTexture
            pbr.name = name
            pbr.metallicFactor, pbr.roughnessFactor = 0.0, 0.7
            g.visual = trimesh.visual.TextureVisuals(uv=g.visual.uv, material=pbr)
            parts.append((name, g))
        parts.sort(key=lambda p: p[0])
        root = np.diag([0.01, 0.01, 0.01, 1.0])  # centimetres -> metres
        export_glb(os.path.join(out, "multi_material.glb"), parts, root=("deck_chair", root))

        write_licenses(out, npm_ver, npm_lic, deb_ver, pypi_ver, skimage.__version__, props)
    finally:
        if args.work is None and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    log("done:", out)


def sh3d_entry(props, model_dir):
    """name/creator of the catalog entry whose model lives in /blendswap-cc-0/<model_dir>/."""
    kv = dict(line.split("=", 1) for line in props.splitlines() if "=" in line and not line.startswith("#"))
    for k, val in kv.items():
        if k.startswith("model#") and val.startswith(f"/blendswap-cc-0/{model_dir}/"):
            n = k.split("#")[1]
            return kv.get(f"name#{n}"), kv.get(f"creator#{n}"), val
    return None, None, None


def write_licenses(out, npm_ver, npm_lic, deb_ver, pypi_ver, sk_ver, props):
    npm = f"npm {NPM_PKG} {npm_ver} (license {npm_lic})"
    deb = f"Debian {DEB_PKG} {deb_ver}, {SH3D_CATALOG}"
    sk = f"PyPI scikit-image {sk_ver}"
    crate_name, crate_by, crate_model = sh3d_entry(props, "crate")
    chair_name, chair_by, chair_model = sh3d_entry(props, "deckChair")
    rows = [
        ("textures/brick.png", f"{sk}, skimage/data/brick.png (CC0Textures 'Bricks25'); tinted RGB, 128x128",
         "CC0Textures.com (Lennart Demes)", "CC0-1.0"),
        ("textures/grass.png", f"{sk}, skimage/data/grass.png (DeviantArt linolafett 'Grass-01'); tinted RGB, "
         "128x128", "linolafett", "CC0-1.0"),
        ("textures/gravel.png", f"{sk}, skimage/data/gravel.png (CC0Textures 'Gravel04'); tinted RGB, 128x128",
         "CC0Textures.com (Lennart Demes)", "CC0-1.0"),
        ("bunny.glb", f"{npm}, package/models/bunny.glb.js (Draco GLB, Stanford bunny) decoded with DracoPy, "
         "simplified to ~4k faces, spherical UVs; texture = skimage grass (256x256, tinted)",
         "Stanford Computer Graphics Laboratory / pmndrs; texture linolafett", "CC0-1.0"),
        ("suzanne.glb", f"{npm}, package/models/suzi.glb.js (Draco GLB, Blender's Suzanne) decoded, "
         "simplified to ~4k faces, spherical UVs; texture = skimage gravel (256x256, tinted)",
         "Blender Foundation / pmndrs; texture CC0Textures.com", "CC0-1.0"),
        ("bunny.ply", f"{npm}, package/models/bunny.glb.js, simplified to ~2k faces, rotated to Z-up, "
         "generated vertex colours", "Stanford Computer Graphics Laboratory / pmndrs", "CC0-1.0"),
        ("cube.off", "generated by tools/make_fixtures.py", "meshseal authors", "CC0-1.0"),
        ("tetra.stl", "generated by tools/make_fixtures.py", "meshseal authors", "CC0-1.0"),
        ("teapot/teapot.obj, teapot/teapot.mtl",
         f"PyPI {PYPI_PKG} {pypi_ver} wheel, panda3d/models/teapot.egg.pz converted to OBJ by "
         "tools/make_fixtures.py, spherical UVs added", "Utah teapot (Martin Newell, 1975); Panda3D "
         "(Carnegie Mellon University / Disney)", "BSD-3-Clause (Panda3D's license)"),
        ("teapot/teapot.jpg", f"{sk}, skimage/data/brick.png, tinted RGB, 256x256",
         "CC0Textures.com (Lennart Demes)", "CC0-1.0"),
        ("sh3d_crate/crate.obj, sh3d_crate/crate.mtl, sh3d_crate/BLENDSWAP_LICENSE.html",
         f"{deb} -> {crate_model} ('{crate_name}'), unchanged (licence file renamed from "
         "'71943 - Low poly Crate - License.html')",
         f"{crate_by} (Blend Swap 71943), converted by Emmanuel Puybaret / eTeks", "CC0-1.0"),
        ("sh3d_crate/crate.jpg", f"{deb} -> blendswap-cc-0/crate/crate.jpg, resized 384->256",
         f"{crate_by}", "CC0-1.0"),
        ("sh3d_deckChair/deckChair.obj, deckChair.mtl, BEuropean_Beech.jpg, BlueWhite_Stripes.jpg, "
         "BLENDSWAP_LICENSE.txt", f"{deb} -> {chair_model} ('{chair_name}'), unchanged",
         f"{chair_by} (Blend Swap 66526 'Beach Chairs Set'), converted by Emmanuel Puybaret / eTeks", "CC0-1.0"),
        ("multi_material.glb", "sh3d_deckChair exported with trimesh: nodes frame/fabric/metal under root "
         "node deck_chair (scale 0.01)", f"{chair_by}", "CC0-1.0"),
    ]
    lines = [
        "Test fixtures of meshseal: sources and licenses",
        "=============================================",
        "",
        "Regenerate with: python tools/make_fixtures.py  (needs npm, apt-get, pip; see its docstring).",
        "Only CC0 / BSD / MIT material is used here. CC0 needs no attribution; it is given anyway.",
        "",
    ]
    for f, src, author, lic in rows:
        lines += [f"* {f}", f"    source:  {src}", f"    author:  {author}", f"    license: {lic}", ""]
    lines += [
        "Provenance notes",
        "-" * 16,
        "",
        "* Stanford bunny: @pmndrs/assets ships it as CC0-1.0 (package.json + LICENSE). The original",
        "  Stanford 3D Scanning Repository page has no formal license; it asks that the source be",
        "  acknowledged: Stanford University Computer Graphics Laboratory (Turk & Levoy, 1994).",
        "* Suzanne: Blender's test monkey (Blender Foundation); shipped as CC0-1.0 by @pmndrs/assets.",
        "* Utah teapot: geometry by Martin Newell (1975), widely treated as public domain; the egg file",
        "  is distributed inside the panda3d wheel under Panda3D's BSD-3-Clause license.",
        "* Sweet Home 3D BlendSwap-CC-0 catalog: debian/copyright says 'Files: BlendSwap-CC-0/*,",
        "  Copyright: 2014, Emmanuel PUYBARET eTeks and other contributors, License: CC0'; each model",
        "  folder also carries its Blend Swap CC-Zero license file (copied next to the model here).",
        "",
    ]
    lines += ["Sweet Home 3D models checked and rejected / not used", "-" * 52, ""]
    lines += [f"* {m}: {why}" for m, why in SH3D_REJECTED]
    lines.append("")
    with open(os.path.join(out, "LICENSES"), "w") as fh:
        fh.write("\n".join(lines))


if __name__ == "__main__":
    main()
