"""Merge render-dataset chunks into one dataset folder.

    python -m gf_core.data.merge --out DATASET --frames 0:30 CHUNK0 CHUNK1 ...

Each chunk is ``gf-cli render-dataset`` of the same simulation with the same options and seed on
its own frame range (``render_source.json`` says so and must agree). The images, the
``transforms_{train,test}.json`` entries (frame by frame, views in order; D-NeRF times normalised
again over the whole clip), the ground truth and the source record come out as one render over all
the frames writes them; ``manifest.json`` lists every frame and the chunks' summed render time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from ..errors import InputError
from ..formats.hdf5 import atomic_write_text

SPLITS = ("train", "test")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "missing: this chunk is not a finished render-dataset output") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"is not valid JSON ({e})") from None


def _write_json(path: Path, data) -> None:  # as render_data/render_dataset.py writes them
    atomic_write_text(path, json.dumps(data, indent=1))


def _copy(src: Path, dst: Path) -> None:
    tmp = dst.with_name(dst.name + ".partial")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def merge_datasets(chunks, out, *, frames: str | None = None) -> Path:
    chunks = [Path(c) for c in chunks]
    if not chunks:
        raise InputError("merge", "no chunks given")
    out = Path(out)
    source = _read_json(chunks[0] / "render_source.json")
    for c in chunks[1:]:
        if _read_json(c / "render_source.json") != source:
            raise InputError(c, f"was rendered from another simulation or with other options than {chunks[0]}")
    out.mkdir(parents=True, exist_ok=True)
    for split in SPLITS:
        metas = [(c, c / f"transforms_{split}.json") for c in chunks]
        present = [p.exists() for _, p in metas]
        if not any(present):
            continue
        if not all(present):
            raise InputError(metas[present.index(False)][1], f"missing, while other chunks have a {split} split")
        metas = [(c, _read_json(p)) for c, p in metas]
        head = {k: v for k, v in metas[0][1].items() if k != "frames"}
        entries, seen = [], set()
        for c, m in metas:
            if {k: v for k, v in m.items() if k != "frames"} != head:
                raise InputError(c / f"transforms_{split}.json", f"its cameras or settings differ from {chunks[0]}'s")
            for e in m["frames"]:
                if e["file_path"] in seen:
                    raise InputError(c, f"{e['file_path']} is in two chunks (their frame ranges overlap)")
                seen.add(e["file_path"])
                src = c / e["file_path"]
                if not src.is_file():
                    raise InputError(src, "missing: the chunk's transforms list it")
                entries.append((c, e))
        dnerf = "time_s" in entries[0][1]
        entries.sort(key=lambda ce: (ce[1]["time_s"] if dnerf else ce[1]["frame"], ce[1]["view_id"]))
        if dnerf:  # D-NeRF's [0, 1] spans the whole clip, not each chunk
            t0, t1 = entries[0][1]["time_s"], entries[-1][1]["time_s"]
            for _, e in entries:
                e["time"] = (e["time_s"] - t0) / (t1 - t0) if t1 > t0 else 0.0
        (out / split).mkdir(exist_ok=True)
        for c, e in entries:
            _copy(c / e["file_path"], out / e["file_path"])
        _write_json(out / f"transforms_{split}.json", {**metas[0][1], "frames": [e for _, e in entries]})
    gt = chunks[0] / "gt_sim.h5"
    if gt.exists():
        _copy(gt, out / "gt_sim.h5")
    manifests = [_read_json(c / "manifest.json") for c in chunks]
    manifest = dict(manifests[0])
    manifest["frames"] = sorted(f for m in manifests for f in m["frames"])
    manifest["options"] = dict(manifest["options"], out=str(out), frames=frames or manifest["options"].get("frames"))
    manifest["render_seconds"] = sum(m.get("render_seconds", 0.0) for m in manifests)
    manifest["chunks"] = [str(c) for c in chunks]
    _write_json(out / "manifest.json", manifest)
    _write_json(out / "render_source.json", source)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gf_core.data.merge", description=__doc__.split("\n\n")[0])
    p.add_argument("chunks", nargs="+", type=Path, help="render-dataset outputs of disjoint frame ranges")
    p.add_argument("--out", type=Path, required=True, help="the merged dataset folder")
    p.add_argument("--frames", default=None, help="the whole frame range, recorded in manifest.json")
    a = p.parse_args(argv)
    try:
        merge_datasets(a.chunks, a.out, frames=a.frames)
    except InputError as e:
        print(f"merge: error: {e}", file=sys.stderr)
        return 2
    n = sum(1 for _ in a.out.glob("*/*.png"))
    print(f"merged {len(a.chunks)} chunks into {a.out} ({n} images)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
