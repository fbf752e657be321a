"""``gf-cli addon build``: the installable Blender extension zip.

The zip holds blender_addon/ (manifest, operators, panel, handlers), the toolkit's torch-free
modules it shares with the rest of the toolkit (gf_core: errors and the formats package whole; render_data:
scene_builder, render_dataset -- one implementation, copied at build time), and h5py wheels for
each platform asked for and each Python Blender ships (CPython 3.11: Blender 4.5 - 5.0; 3.13:
5.1 on), downloaded from PyPI into a cache once. Blender installs the wheel that matches the
machine and its Python.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

H5PY_VERSION = "3.16.0"
PYTHONS = ("311", "313")  # CPython tags of Blender's Python: 3.11 in Blender 4.5 - 5.0, 3.13 from 5.1
# Blender's platform names -> pip platform tags that h5py publishes wheels under
PLATFORMS = {
    "linux-x64": ["manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_28_x86_64"],
    "macos-arm64": [f"macosx_{v}_0_arm64" for v in (11, 12, 13, 14, 15)],
    "macos-x64": [f"macosx_10_{v}_x86_64" for v in (9, 13, 15)] + [f"macosx_{v}_0_x86_64" for v in (11, 12, 13, 14, 15)],
    "windows-x64": ["win_amd64"],
}
# files of the toolkit the extension carries; a name ending in / is a whole package
SHARED = {"gf_core": ["__init__.py", "errors.py", "formats/"],
          "render_data": ["__init__.py", "scene_builder.py", "render_dataset.py"]}
ROOT = Path(__file__).resolve().parent.parent


def register(sub):
    p = sub.add_parser("addon", help="build the Blender extension zip",
                       description="Blender extension (Blender >= 4.5). `gf-cli addon build` writes the zip to "
                                   "install with Edit > Preferences > Get Extensions > Install from Disk.")
    asub = p.add_subparsers(dest="addon_command", metavar="ACTION")
    asub.required = True
    b = asub.add_parser("build", help="write the installable extension zip (h5py wheels bundled)")
    b.add_argument("--out", type=Path, default=Path("dist"),
                   help="output folder or .zip path (default: dist/, giving dist/gaussfluids-VERSION.zip)")
    b.add_argument("--platforms", default=",".join(PLATFORMS),
                   help=f"comma-separated Blender platforms to bundle h5py for (default: {','.join(PLATFORMS)})")
    b.add_argument("--wheel-cache", type=Path, default=None,
                   help="where downloaded wheels are kept (default: ~/.cache/gaussfluids/wheels)")
    b.set_defaults(func=run_build)


def parse_platforms(spec: str) -> list[str]:
    from gf_core.errors import InputError

    plats = [s.strip() for s in spec.split(",") if s.strip()]
    bad = [s for s in plats if s not in PLATFORMS]
    if bad or not plats:
        raise InputError("--platforms", f"unknown platform(s) {bad or spec!r}; choose from {', '.join(PLATFORMS)}")
    return list(dict.fromkeys(plats))


def _wheel_platforms(name: str) -> set:
    # h5py-3.16.0-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl
    return set(name[:-4].split("-")[-1].split("."))


def find_wheel(cache: Path, platform: str, python: str = "311") -> Path | None:
    tags = set(PLATFORMS[platform])
    for w in sorted(cache.glob(f"h5py-{H5PY_VERSION}-cp{python}-cp{python}-*.whl")):
        if _wheel_platforms(w.name) & tags:
            return w
    return None


def fetch_wheel(cache: Path, platform: str, python: str = "311") -> Path:
    """The h5py wheel for ``platform`` and CPython ``python`` ("311"), from the cache or
    downloaded from PyPI with pip."""
    from gf_core.errors import GFError

    w = find_wheel(cache, platform, python)
    if w is not None:
        return w
    cache.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", f"h5py=={H5PY_VERSION}", "--only-binary=:all:", "--no-deps",
           "--python-version", f"{python[0]}.{python[1:]}", "--implementation", "cp", "--abi", f"cp{python}",
           "-d", str(cache),
           "--disable-pip-version-check", "--quiet"]
    for tag in PLATFORMS[platform]:
        cmd += ["--platform", tag]
    r = subprocess.run(cmd, capture_output=True, text=True)
    w = find_wheel(cache, platform, python)
    if r.returncode != 0 or w is None:
        tail = (r.stderr or r.stdout).strip().splitlines()[-3:]
        raise GFError(f"could not download the h5py {H5PY_VERSION} wheel for {platform}, CPython {python}, from PyPI "
                      f"into {cache} (offline?). pip said: {' | '.join(tail) or 'nothing'}. Run once with network access, put the "
                      f"wheel into {cache} by hand, or leave that platform out with --platforms.")
    return w


def manifest_text(platforms: list[str], wheels: list[str]) -> str:
    text = (ROOT / "blender_addon" / "blender_manifest.toml").read_text()
    extra = (f"platforms = [{', '.join(repr(p).replace(chr(39), chr(34)) for p in platforms)}]\n"
             f"wheels = [{', '.join(chr(34) + './wheels/' + w + chr(34) for w in wheels)}]\n\n")
    return text.replace("[permissions]", extra + "[permissions]", 1)


def addon_version() -> str:
    m = re.search(r'^version\s*=\s*"([^"]+)"', (ROOT / "blender_addon" / "blender_manifest.toml").read_text(), re.M)
    return m.group(1)


def build(out: Path, platforms: list[str], cache: Path) -> Path:
    """Write the zip; returns its path. Fails before writing anything if a wheel is missing."""
    from gf_core.formats.hdf5 import atomic_path

    wheels = [fetch_wheel(cache, p, py) for p in platforms for py in PYTHONS]
    out = Path(out)
    target = out if out.suffix == ".zip" else out / f"gaussfluids-{addon_version()}.zip"
    files = {}
    for f in sorted((ROOT / "blender_addon").glob("*.py")):
        files[f.name] = f
    for pkg, names in SHARED.items():
        for n in names:
            for src in (sorted((ROOT / pkg / n).glob("*.py")) if n.endswith("/") else [ROOT / pkg / n]):
                text = src.read_text()
                if re.search(r"^\s*(import torch|from torch)", text, re.M):
                    raise RuntimeError(f"{src} imports torch and cannot go into the Blender extension")
                files[src.relative_to(ROOT).as_posix()] = src
    with atomic_path(target) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("blender_manifest.toml", manifest_text(platforms, [w.name for w in wheels]))
            for arc, src in files.items():
                z.write(src, arc)
            for w in wheels:
                z.write(w, f"wheels/{w.name}")
    return target


def run_build(args) -> int:
    platforms = parse_platforms(args.platforms)
    cache = args.wheel_cache or Path(os.environ.get("GF_WHEEL_CACHE", Path.home() / ".cache" / "gaussfluids" / "wheels"))
    path = build(args.out, platforms, cache)
    size = path.stat().st_size / 1e6
    print(f"wrote {path} ({size:.1f} MB; h5py {H5PY_VERSION} for {', '.join(platforms)}, "
          f"CPython {' and '.join(p[0] + '.' + p[1:] for p in PYTHONS)})")
    print("install: Blender > Edit > Preferences > Get Extensions > (menu) Install from Disk...")
    return 0
