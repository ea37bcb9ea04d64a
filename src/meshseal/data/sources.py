"""Where the assets come from: Debian packages fetched with `apt-get download`, or a user's folder.

Each source yields `Asset`s (one mesh each, with provenance: package, version, original path,
category, creator, license, and a *group* key: items of one group never straddle the train/test
split) and `TextureCandidate`s (real images for the texture pool).
"""

from __future__ import annotations

import hashlib
import io
import re
import shutil
import subprocess
import sys
import tarfile
import urllib.parse
import xml.etree.ElementTree as ET
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..errors import MeshsealError


class DataError(MeshsealError):
    """A data source or dataset folder is unusable."""


@dataclass
class Asset:
    id: str
    source: str
    source_version: str
    original_path: str
    path: str  # local file to read
    name: str
    category: str
    source_category: str
    creator: str
    license: str
    group: str
    texture_path: str | None = None
    rotation: list | None = None  # 3x3 row-major, applied before anything else (SH3D modelRotation)
    split_hint: str | None = None
    search_roots: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TextureCandidate:
    source: str
    source_version: str
    license: str
    original_path: str
    archive: str | None  # a zip/pk3 file holding `member`, or None for a plain file at original_path
    member: str


# ------------------------------------------------------------------ categories

# ModelNet40 names first, then a few labels ModelNet lacks (building, ship, tree -> plant, ...).
CATEGORY_KEYWORDS = [
    ("airplane", r"airplane|aircraft|aeroplane|plane\b|jet\b|glider|kc-?1|a4-f|helicopter|cessna"),
    ("bathtub", r"bathtub|\bbath\b|jacuzzi|islandbath"),
    ("toilet", r"toilet|\bwc\b|urinal|bidet"),
    ("sink", r"sink|washbasin|basin|lavabo"),
    ("bed", r"\bbed|bunk|futon|cradle|crib|hammock|mattress"),
    ("night_stand", r"nightstand|night_stand|bedside"),
    ("bench", r"bench"),
    ("bookshelf", r"bookcase|bookshelf|shelf|shelves|etagere"),
    ("bottle", r"bottle|amphora|jar\b"),
    ("bowl", r"bowl"),
    ("car", r"\bcar\b|car_|sedan|suv|van\b|truck|bus\b|jeep|taxi|peugeot|renault|chevrolet|smart-car|vehicle|"
            r"tractor|pickup|lorry|cart\b|wagon|chariot|pushback|scooter|motorbike|yamaha|bicycle|tricycle"),
    ("chair", r"chair|armchair|stool|seat|rocking"),
    ("cone", r"\bcone"),
    ("cup", r"\bcup\b|mug|glass\b|teacup"),
    ("curtain", r"curtain|blind"),
    ("desk", r"\bdesk"),
    ("door", r"door|gate\b"),
    ("dresser", r"dresser|chest|drawer|commode|cabinet|cupboard|sideboard|buffet"),
    ("flower_pot", r"flower|pot_plant|plant_pot|planter"),
    ("guitar", r"guitar"),
    ("keyboard", r"keyboard"),
    ("lamp", r"lamp|light|lantern|chandelier|candle|sconce|torch"),
    ("laptop", r"laptop|notebook"),
    ("mantel", r"fireplace|chimney|mantel"),
    ("monitor", r"monitor|screen|\btv\b|television|computer"),
    ("person", r"person|man\b|woman|male|female|girl|boy|child|people|sit(male|female)|mannequin|character"),
    ("piano", r"piano"),
    ("plant", r"plant|tree|palm|bush|shrub|hedge|bamboo|ficus|bonsai|cactus|fern|grass|pine|oak|maple|"
              r"cypress|baobab|banyan|acacia|banana|birch|leaves|sapling|poplar|willow|olive|fir\b|yucca"),
    ("radio", r"radio|stereo|speaker|hifi"),
    ("range_hood", r"hood"),
    ("sofa", r"sofa|couch|settee|divan|loveseat"),
    ("stairs", r"stair|ladder|escalator"),
    ("table", r"table"),
    ("tent", r"tent\b|tent_|tepee|yurt"),
    ("tv_stand", r"tv_stand|tv-stand|tvstand|media"),
    ("vase", r"vase|urn"),
    ("wardrobe", r"wardrobe|closet|armoire|locker"),
    ("xbox", r"xbox|playstation|console"),
    ("ship", r"ship|boat|ferry|carrier|nimitz|clemenceau|yacht|barge|trireme|galley|maritime|vessel|sail"),
    ("building", r"building|house|apartment|barrack|tower|temple|church|hangar|office|station|farm|stable|"
                 r"barn|silo|hall|castle|fort|wall|structural|residential|commercial|industrial|warehouse|"
                 r"shop|store|cottage|villa|hut|palace|civil_centre|market|dock|storehouse|garage|shed"),
    ("rock", r"rock|stone|boulder|cliff|ore|mine\b"),
    ("animal", r"horse|camel|elephant|dog\b|cat\b|cow|sheep|pig|rabbit|deer|bird|fish|zebu|animal"),
    ("weapon", r"sword|spear|axe\b|bow\b|arrow|shield|helmet|armor|armour|greave|weapon|quiver|catapult|"
               r"ballista|siege|ram\b|bomb|missile|gun"),
    ("kitchen", r"oven|cooker|fridge|refrigerator|dishwasher|microwave|kettle|toaster|kitchen|stove"),
    ("appliance", r"washing|dryer|heater|air-condition|conditioning|fan\b|radiator|printer|phone|camera"),
    ("window", r"window"),
    ("fence", r"fence|railing|barrier|palisade"),
]
MODELNET40 = set("airplane bathtub bed bench bookshelf bottle bowl car chair cone cup curtain desk door dresser "
                 "flower_pot glass_box guitar keyboard lamp laptop mantel monitor night_stand person piano plant "
                 "radio range_hood sink sofa stairs stool table tent toilet tv_stand vase wardrobe xbox".split())
_CATEGORY_RE = [(label, re.compile(pattern)) for label, pattern in CATEGORY_KEYWORDS]


def categorize(*texts: str, default: str = "other") -> str:
    """A ModelNet-like label from names and paths (first keyword that matches, most specific text first)."""
    for text in texts:
        if not text:
            continue
        lowered = re.sub(r"([a-z])([A-Z])", r"\1 \2", text).lower()
        for label, pattern in _CATEGORY_RE:
            if pattern.search(lowered):
                return label
    return default


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:80] or "item"


# ------------------------------------------------------------------ Debian packages


def fetch_deb(package: str, cache: Path, log=print) -> Path:
    """The package's .deb in `cache`, downloaded with `apt-get download` unless already there."""
    cache.mkdir(parents=True, exist_ok=True)
    existing = sorted(cache.glob(f"{package}_*.deb"))
    if existing:
        return existing[-1]
    if shutil.which("apt-get") is None:
        raise DataError(f"cannot fetch {package}: apt-get is not available (use --from-folder)")
    log(f"downloading {package} with apt-get download ...")
    result = subprocess.run(["apt-get", "download", "-q", package], cwd=cache, capture_output=True, text=True)
    existing = sorted(cache.glob(f"{package}_*.deb"))
    if result.returncode != 0 or not existing:
        detail = (result.stderr.strip().splitlines() or ["no output"])[-1]
        raise DataError(f"cannot download {package}: {detail}")
    return existing[-1]


def deb_version(deb: Path) -> str:
    parts = deb.name[:-4].split("_")
    return urllib.parse.unquote(parts[1]) if len(parts) >= 3 else "unknown"


def _deb_tar_stream(deb: Path):
    """Yield a streaming tarfile of the package's data archive (dpkg-deb if present, else ar + tarfile)."""
    if shutil.which("dpkg-deb"):
        process = subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE)
        try:
            with tarfile.open(fileobj=process.stdout, mode="r|") as archive:
                yield archive
        finally:
            process.stdout.close()
            process.wait()
        return
    with open(deb, "rb") as handle:
        if handle.read(8) != b"!<arch>\n":
            raise DataError(f"{deb}: not a Debian package")
        while True:
            header = handle.read(60)
            if len(header) < 60:
                raise DataError(f"{deb}: no data archive inside")
            name, size = header[:16].decode().strip().rstrip("/"), int(header[48:58].decode().strip())
            if name.startswith("data.tar"):
                mode = {"data.tar.xz": "r|xz", "data.tar.gz": "r|gz", "data.tar.bz2": "r|bz2",
                        "data.tar": "r|"}.get(name)
                if mode is None:
                    raise DataError(f"{deb}: {name} needs dpkg-deb to unpack")
                with tarfile.open(fileobj=_Limited(handle, size), mode=mode) as archive:
                    yield archive
                return
            handle.seek(size + (size & 1), 1)


class _Limited(io.RawIOBase):
    def __init__(self, handle, size):
        self.handle, self.left = handle, size

    def readable(self):
        return True

    def readinto(self, buffer):
        n = min(len(buffer), self.left)
        data = self.handle.read(n)
        buffer[:len(data)] = data
        self.left -= len(data)
        return len(data)


def extract_deb(deb: Path, dest: Path, keep) -> Path:
    """Extract the members for which keep(path) is true into dest (once; a marker makes it resumable)."""
    marker = dest / ".complete"
    if marker.is_file():
        return dest
    dest.mkdir(parents=True, exist_ok=True)
    for archive in _deb_tar_stream(deb):
        for member in archive:
            name = member.name.lstrip("./")
            if not member.isfile() or not keep(name):
                continue
            target = dest / name
            target.parent.mkdir(parents=True, exist_ok=True)
            source = archive.extractfile(member)
            with open(target, "wb") as handle:
                shutil.copyfileobj(source, handle, 1 << 20)
    marker.write_text("ok\n")
    return dest


# ------------------------------------------------------------------ Sweet Home 3D furniture

SH3D_LICENSES = {"BlendSwap-CC-0": "CC0-1.0", "BlendSwap-CC-BY": "CC-BY-3.0", "KatorLegaz": "CC-BY-3.0-US",
                 "Reallusion": "CC-BY-3.0-US", "Scopia": "CC-BY-3.0"}


def parse_properties(text: str) -> dict[str, str]:
    """Java .properties (key=value, backslash escapes, \\uXXXX)."""
    result = {}
    logical = re.sub(r"\\\r?\n\s*", "", text)
    for line in logical.splitlines():
        line = line.strip()
        if not line or line[0] in "#!":
            continue
        match = re.match(r"((?:\\.|[^=:\s])+)\s*[=:\s]\s*(.*)", line)
        if not match:
            continue
        key, value = match.groups()

        def unescape(s):
            s = re.sub(r"\\u([0-9a-fA-F]{4})", lambda m: chr(int(m.group(1), 16)), s)
            return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s)

        result[unescape(key)] = unescape(value)
    return result


def sweethome3d_source(cache: Path, log=print):
    package = "sweethome3d-furniture"
    deb = fetch_deb(package, cache, log)
    version = deb_version(deb)
    root = extract_deb(deb, cache / "extract" / f"{package}_{version.replace(':', '_')}", lambda n: n.endswith(".sh3f"))
    assets, textures = [], []
    for sh3f in sorted(root.rglob("*.sh3f")):
        catalog = sh3f.stem
        folder = sh3f.parent / f"{catalog}.d"
        if not (folder / ".complete").is_file():
            with zipfile.ZipFile(sh3f) as archive:
                archive.extractall(folder)
            (folder / ".complete").write_text("ok\n")
        props = parse_properties((folder / "PluginFurnitureCatalog.properties").read_text("latin-1"))
        license_ = SH3D_LICENSES.get(catalog, props.get("license", "unknown"))
        index = 1
        while f"model#{index}" in props:
            model = props[f"model#{index}"].lstrip("/")
            name = props.get(f"name#{index}", Path(model).stem)
            category = props.get(f"category#{index}", "")
            creator = props.get(f"creator#{index}", catalog)
            rotation = None
            if f"modelRotation#{index}" in props:
                values = [float(v) for v in props[f"modelRotation#{index}"].split()]
                rotation = values if len(values) == 9 else None
            path = folder / model
            assets.append(Asset(
                id=f"sh3d-{slug(catalog)}-{slug(Path(model).parent.name or Path(model).stem)}",
                source=package, source_version=version,
                original_path=f"{sh3f.relative_to(root)}:{model}", path=str(path), name=name,
                category=categorize(name, Path(model).stem, category), source_category=category,
                creator=creator, license=license_, group=f"sh3d/{catalog}/{creator}", rotation=rotation))
            index += 1
        for image in sorted(folder.rglob("*")):
            if image.suffix.lower() in {".jpg", ".jpeg", ".png"} and image.parent != folder:
                textures.append(TextureCandidate(package, version, license_,
                                                 f"{sh3f.relative_to(root)}:{image.relative_to(folder)}",
                                                 None, str(image)))
    return assets, textures


# ------------------------------------------------------------------ FlightGear scenery models

FG_SKIP = {"Weather", "Effects", "Astro", "Volcanoes"}


def flightgear_source(cache: Path, log=print):
    package = "flightgear-data-models"
    deb = fetch_deb(package, cache, log)
    version = deb_version(deb)
    suffixes = {".ac", ".rgb", ".rgba", ".png", ".jpg", ".dds", ".sgi"}
    root = extract_deb(deb, cache / "extract" / f"{package}_{version.replace(':', '_')}",
                       lambda n: "/Models/" in n and Path(n).suffix.lower() in suffixes)
    models = next((p for p in root.rglob("Models") if p.is_dir()), None)
    assets = []
    if models is None:
        return assets, []
    for ac in sorted(models.rglob("*.ac")):
        rel = ac.relative_to(models)
        if rel.parts[0] in FG_SKIP:
            continue
        folder = "/".join(rel.parts[:-1]) or "."
        assets.append(Asset(
            id=f"fg-{slug(str(rel.with_suffix('')))}", source=package, source_version=version,
            original_path=str(ac.relative_to(root)), path=str(ac), name=ac.stem,
            category=categorize(ac.stem, str(rel.parent)), source_category=folder,
            creator="FlightGear contributors", license="GPL-2+", group="fg/" + ("/".join(rel.parts[:-1][:2]) or "."),
            search_roots=[str(ac.parent), str(models)]))
    return assets, []


# ------------------------------------------------------------------ 0 A.D. art

ZERO_AD_DIRS = ("art/meshes/structural/", "art/meshes/gaia/", "art/meshes/props/")
ZERO_AD_PER_GROUP = 6


def zero_ad_source(cache: Path, log=print):
    package = "0ad-data"
    deb = fetch_deb(package, cache, log)
    version = deb_version(deb)
    root = cache / "extract" / f"{package}_{version.replace(':', '_')}"
    marker = root / ".complete"
    if not marker.is_file():
        log("unpacking 0ad-data (one large archive, about two minutes) ...")
        staging = extract_deb(deb, root / "staging", lambda n: n.endswith("public/public.zip"))
        public = next(staging.rglob("public.zip"))
        texture_of: dict[str, str] = {}
        with zipfile.ZipFile(public) as archive:
            names = archive.namelist()
            present = set(names)
            for name in names:
                if not (name.startswith("art/actors/") and name.endswith(".xml")):
                    continue
                try:
                    tree = ET.fromstring(archive.read(name))
                except ET.ParseError:
                    continue
                for variant in tree.iter("variant"):
                    mesh = variant.findtext("mesh")
                    textures = variant.find("textures")
                    base = None
                    if textures is not None:
                        for texture in textures.iter("texture"):
                            if texture.get("name") in ("baseTex", None) and texture.get("file"):
                                base = texture.get("file")
                                break
                    if mesh and base:
                        texture_of.setdefault(mesh.strip(), base.strip())
            wanted = [n for n in names if n.startswith(ZERO_AD_DIRS) and n.endswith(".dae.cached.pmd")]
            lines = []
            for name in wanted:
                mesh_key = name[len("art/meshes/"):-len(".cached.pmd")]
                texture = texture_of.get(mesh_key)
                texture_member = None
                if texture:
                    for candidate in (f"art/textures/skins/{texture}.cached.dds", f"art/textures/skins/{texture}"):
                        if candidate in present:
                            texture_member = candidate
                            break
                for member in filter(None, (name, texture_member)):
                    target = root / member
                    if not target.is_file():
                        target.parent.mkdir(parents=True, exist_ok=True)
                        target.write_bytes(archive.read(member))
                lines.append(f"{name}\t{texture_member or ''}")
        (root / "index.tsv").write_text("\n".join(lines) + "\n")
        shutil.rmtree(root / "staging", ignore_errors=True)  # 3 GB archive: keep only what we use
        marker.write_text("ok\n")
    assets = []
    per_group: Counter = Counter()
    for line in (root / "index.tsv").read_text().splitlines():
        if not line.strip():
            continue
        name, texture_member = (line.split("\t") + [""])[:2]
        if not texture_member:
            continue  # meshes whose actor names no base texture are mostly helpers and decals
        rel = name[len("art/meshes/"):-len(".dae.cached.pmd")]
        group = f"0ad/{rel.split('/')[0]}/{Path(rel).name.split('_')[0]}"
        per_group[group] += 1
        if per_group[group] > ZERO_AD_PER_GROUP:
            continue  # many near-variants (helmets, shields, ...): keep a few per family
        rel = name[len("art/meshes/"):-len(".dae.cached.pmd")]
        top = rel.split("/")[0]
        stem = Path(rel).name
        prefix = stem.split("_")[0]
        assets.append(Asset(
            id=f"0ad-{slug(rel)}", source=package, source_version=version, original_path=f"public.zip:{name}",
            path=str(root / name), name=stem, category=categorize(stem, rel), source_category=str(Path(rel).parent),
            creator="Wildfire Games", license="CC-BY-SA-3.0", group=f"0ad/{top}/{prefix}",
            texture_path=str(root / texture_member) if texture_member else None))
    return assets, []


# ------------------------------------------------------------------ texture-only packages

TEXTURE_PACKAGES = {
    "nexuiz": ("nexuiz-textures", "GPL-2+"),
    "openarena": ("openarena-081-textures", "GPL-2+"),
}
_SKIP_TEXTURE = re.compile(r"(_norm|_gloss|_glow|_bump|_shirt|_pants|_reflect|_spec|_luma|_local|_height|_nm|"
                           r"_blend|_add|_alpha|_mask|_d\b)|(^|/)(sfx|skies|sky|env|effects|fx|lights?|common|"
                           r"liquids?|water|fog|logos?|decals?|gfx|particles|flares?|menu|ui|fonts?|"
                           r"lightning|lava|slime|portal)/", re.I)


def texture_package_source(key: str, cache: Path, log=print):
    from .formats import IMAGE_SUFFIXES  # numpy and PIL: not imported to build the command line's parser

    package, license_ = TEXTURE_PACKAGES[key]
    deb = fetch_deb(package, cache, log)
    version = deb_version(deb)
    root = extract_deb(deb, cache / "extract" / f"{package}_{version.replace(':', '_')}",
                       lambda n: n.endswith(".pk3") or Path(n).suffix.lower() in IMAGE_SUFFIXES)
    candidates = []
    for archive_path in sorted(root.rglob("*.pk3")):
        with zipfile.ZipFile(archive_path) as archive:
            for name in sorted(archive.namelist()):
                if Path(name).suffix.lower() in {".tga", ".jpg", ".jpeg", ".png"} and name.startswith("textures/") \
                        and not _SKIP_TEXTURE.search(name):
                    candidates.append(TextureCandidate(package, version, license_,
                                                       f"{archive_path.relative_to(root)}:{name}",
                                                       str(archive_path), name))
    return [], candidates


# ------------------------------------------------------------------ a user's folder


def existing_folder(folder) -> Path:
    """`folder` as a Path; DataError where it is not a folder (checked by the command line before the
    build's heavy imports, so that a mistyped name is answered at once)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: no such folder")
    return folder


def manifest_path(root) -> Path:
    """A dataset's manifest.jsonl; DataError where `root` holds none (not a dataset built by `meshseal
    data build`)."""
    path = Path(root) / "manifest.jsonl"
    if not path.is_file():
        raise DataError(f"{root}: not a meshseal dataset (no manifest.jsonl; run 'meshseal data build')")
    return path


def folder_source(folder: Path, license_: str = "unknown", creator: str = "unknown"):
    """Meshes under `folder`; the category is the nearest folder name that is not train/test."""
    from .formats import MESH_SUFFIXES  # numpy and PIL: not imported to build the command line's parser

    folder = existing_folder(folder)
    assets = []
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES):
        rel = path.relative_to(folder)
        parents = [p for p in rel.parts[:-1]]
        hint = next((p.lower() for p in reversed(parents) if p.lower() in ("train", "test")), None)
        named = [p for p in parents if p.lower() not in ("train", "test")]
        source_category = named[-1] if named else ""
        stem = path.stem
        root_name = re.sub(r"[_\-\s]*\d+$", "", stem) or stem
        digest = hashlib.sha1(str(rel).encode()).hexdigest()[:6]
        assets.append(Asset(
            id=f"dir-{slug(str(rel.with_suffix('')))}-{digest}", source=f"folder:{folder.name}", source_version="",
            original_path=str(rel), path=str(path), name=stem,
            category=source_category.lower() if source_category.lower() in MODELNET40 else
            categorize(source_category, stem,
                       default=slug(source_category).lower() if source_category else "other"),
            source_category=source_category, creator=creator, license=license_,
            group=f"dir/{'/'.join(named)}/{root_name}", split_hint=hint, search_roots=[str(path.parent)]))
    return assets


def image_folder_textures(folder: Path, license_: str = "unknown"):
    from .formats import IMAGE_SUFFIXES  # numpy and PIL: not imported to build the command line's parser

    folder = existing_folder(folder)
    return [TextureCandidate(f"folder:{folder.name}", "", license_, str(p.relative_to(folder)), None, str(p))
            for p in sorted(folder.rglob("*")) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]


MESH_SOURCES = {"sweethome3d": sweethome3d_source, "flightgear": flightgear_source, "0ad": zero_ad_source}
DEFAULT_SOURCES = ("sweethome3d", "flightgear", "0ad")
DEFAULT_TEXTURE_SOURCES = ("nexuiz", "openarena", "sweethome3d")


def warn(message: str) -> None:
    print(f"meshseal: warning: {message}", file=sys.stderr)
