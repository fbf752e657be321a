"""The demo's ``report.html``: one self-contained page (every image embedded as a data URI, no
network) with the input frames, reconstructed views beside the held-out truth, particle renders
(whole and cut open, against the true particles), the predicted and edited continuations, the
restyled Blender renders, an animated preview (GIF) and every plot. The images it makes are also
written beside it under ``OUT/report/``."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np
import torch


def _uri(path: Path) -> str:
    mime = {".png": "image/png", ".gif": "image/gif"}[path.suffix]
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode()


def _composite(ds, i) -> np.ndarray:
    img, alpha = ds.load(i)
    img = np.asarray(img, np.float32)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, -1)
    if alpha is not None:
        bg = np.asarray(ds.background, np.float32)[:3]
        img = img * alpha[..., None] + bg * (1 - alpha[..., None])
    return np.clip(img, 0, 1)


def _render(params: dict, camera, sh_degree: int, bg=(0.0, 0.0, 0.0)) -> np.ndarray:
    from gf_core.render import render

    with torch.no_grad():
        o = render(params["means"], params["scales"], params["quats"], params["opacities"], params["sh"], camera,
                   torch.tensor(bg, dtype=torch.float32)[:params["sh"].shape[-1]], sh_degree=sh_degree)
    img = o.color.numpy()
    return np.clip(np.repeat(img, 3, -1) if img.shape[-1] == 1 else img, 0, 1)


def _dots(points: np.ndarray, camera, radius: float, color, cut_towards=None) -> np.ndarray:
    """Particles as small opaque dots, shaded by depth; with ``cut_towards`` (the camera centre),
    the half of the fluid nearer the camera is removed to show the inside."""
    from gf_core.render import render_points

    p = np.asarray(points, np.float64)
    if cut_towards is not None and len(p):
        c = p.mean(0)
        p = p[(p - c) @ (np.asarray(cut_towards) - c) <= 0]
    if len(p) == 0:
        return np.zeros((camera.height, camera.width, 3), np.float32)
    with torch.no_grad():
        o = render_points(p.astype(np.float32), camera, radius=radius, color=color, opacity=0.95,
                          background=torch.ones(3))
    return np.clip(o.color.numpy(), 0, 1)


def _grid(rows: list[list[np.ndarray]], pad: int = 2) -> np.ndarray:
    h = max(im.shape[0] for r in rows for im in r)
    w = max(im.shape[1] for r in rows for im in r)
    out = np.ones((len(rows) * (h + pad) - pad, max(len(r) for r in rows) * (w + pad) - pad, 3), np.float32)
    for i, r in enumerate(rows):
        for j, im in enumerate(r):
            out[i * (h + pad):i * (h + pad) + im.shape[0], j * (w + pad):j * (w + pad) + im.shape[1]] = im[..., :3]
    return out


def _upscale(img: np.ndarray, min_size: int = 192) -> np.ndarray:
    k = max(1, int(np.ceil(min_size / img.shape[0])))
    return np.kron(img, np.ones((k, k, 1), np.float32)) if k > 1 else img


def write(d, t_last: float) -> Path:
    """Build ``d.out/report.html`` from the demo's outputs (``d``: gf_cli.cmd_demo.Demo)."""
    from PIL import Image

    from gf_core.camera import frontal_arc
    from gf_core.data import load_dataset
    from gf_core.data.images import write_png
    from gf_core.eval.evaluate import continuation_appearance
    from gf_core.formats.hdf5 import read_recon, read_sim
    from gf_core.recon.model import FluidModel

    out = d.out
    rdir = out / "report"
    rdir.mkdir(parents=True, exist_ok=True)
    train = load_dataset(d.dataset)
    test = load_dataset(d.dataset, split="test")
    gt = read_sim(d.sim)
    r = read_recon(d.run_dir / "recon.h5")
    model = FluidModel.from_recon(r)
    times = train.times
    clip = times[times <= r.time_max + 1e-6]
    view = test.views[0]
    tcam = test.frames[test.indices(view_id=view)[0]].camera
    spacing = 2 * gt.particle_radius
    images = {}

    # 1. input frames: the five training views at three times
    picks = [clip[0], clip[len(clip) // 2], clip[-1]]
    rows = [[_composite(train, train.indices(view_id=v, time=float(t))[0]) for v in train.views] for t in picks]
    write_png(rdir / "input_frames.png", _upscale(_grid(rows), 384))
    images["input"] = rdir / "input_frames.png"

    # 2. held-out view: truth above, reconstruction below, over the reconstructed clip
    sel = clip[np.linspace(0, len(clip) - 1, min(5, len(clip))).round().astype(int)]
    truth = [_composite(test, test.indices(view_id=view, time=float(t))[0]) for t in sel]
    with torch.no_grad():
        recon_imgs = [_render(model.at(float(t)), tcam, model.sh_degree, train.background) for t in sel]
    write_png(rdir / "heldout_vs_recon.png", _upscale(_grid([truth, recon_imgs]), 256))
    images["heldout"] = rdir / "heldout_vs_recon.png"

    # 3. particles: reconstructed (blue) vs true (orange), whole and cut open towards the camera,
    #    seen by a camera framing the fluid over the clip (256 px)
    frames_gt = [int(np.argmin(np.abs(gt.times - t))) for t in sel[[0, len(sel) // 2, -1]]]
    pts = np.concatenate([gt.positions[f] for f in frames_gt])
    lo, hi = pts.min(0), pts.max(0)
    fx = 0.5 * 256 / np.tan(np.radians(20))
    pcam = frontal_arc(1, radius=0.8 * float(np.linalg.norm(hi - lo)) / np.tan(np.radians(20)) / 2 + 0.1,
                       target=0.5 * (lo + hi), height=0.25 * float(np.linalg.norm(hi - lo)), fx=fx, width=256,
                       height_px=256)[0]
    prow, crow = [], []
    for t, f in zip(sel[[0, len(sel) // 2, -1]], frames_gt):
        with torch.no_grad():
            p = model.at(float(t))["means"].numpy()
        for pos, col in ((p, (0.2, 0.45, 0.9)), (gt.positions[f], (0.95, 0.5, 0.1))):
            prow.append(_dots(pos, pcam, 0.3 * spacing, col))
            crow.append(_dots(pos, pcam, 0.3 * spacing, col, pcam.center))
    write_png(rdir / "particles.png", _grid([prow, crow]))
    images["particles"] = rdir / "particles.png"

    # 4. continuations: predicted frames vs truth (held-out view), edited frames
    pred = read_sim(d.pred_dir / "predict.h5")
    _, plook = continuation_appearance(pred, d.pred_dir / "predict.h5")
    ptimes = [t for t in pred.times[1:] if test.indices(view_id=view, time=float(t))]

    def cont_img(sim, look, f):
        return _render({"means": torch.as_tensor(sim.positions[f]), **look}, tcam, model.sh_degree, train.background)

    if ptimes:
        pk = [int(np.argmin(np.abs(pred.times - t))) for t in ptimes]
        pk = [pk[i] for i in np.linspace(0, len(pk) - 1, min(4, len(pk))).round().astype(int)]
        rows = [[_composite(test, test.indices(view_id=view, time=float(pred.times[f]))[0]) for f in pk],
                [cont_img(pred, plook, f) for f in pk]]
        write_png(rdir / "prediction.png", _upscale(_grid(rows), 256))
        images["prediction"] = rdir / "prediction.png"
    edit = read_sim(d.pred_dir / "edit.h5")
    _, elook = continuation_appearance(edit, d.pred_dir / "edit.h5")
    ek = sorted({0, edit.num_frames // 2, edit.num_frames - 1})
    write_png(rdir / "edit.png", _upscale(_grid([[cont_img(edit, elook, f) for f in ek]]), 128))
    images["edit"] = rdir / "edit.png"

    # 5. animated preview: held-out truth | reconstruction (then prediction past the clip)
    frames = []
    for t in times:
        idx = test.indices(view_id=view, time=float(t))
        if not idx:
            continue
        if t <= r.time_max + 1e-6:
            with torch.no_grad():
                ours = _render(model.at(float(t)), tcam, model.sh_degree, train.background)
        else:
            f = int(np.argmin(np.abs(pred.times - t)))
            if abs(pred.times[f] - t) > 0.5 / pred.fps:
                break
            ours = cont_img(pred, plook, f)
        frames.append(_upscale(_grid([[_composite(test, idx[0]), ours]]), 160))
    gif = rdir / "preview.gif"
    pil = [Image.fromarray((255 * f).astype(np.uint8)) for f in frames]
    pil[0].save(gif, save_all=True, append_images=pil[1:], duration=int(1000 / train.meta.get("fps", 10) * 2), loop=0)
    images["preview"] = gif

    ev = json.loads((d.run_dir / "eval.json").read_text())
    pev = json.loads((d.pred_dir / "predict_eval.json").read_text())
    plots = [d.run_dir / p for p in ev.get("plots", [])] + [d.pred_dir / p for p in pev.get("plots", [])]
    looks = [out / "blender" / f"look_{k}.png" for k in ("water", "pink")]

    def fig(path, caption):
        return (f'<figure><img src="{_uri(path)}" alt="{html.escape(caption)}">'
                f"<figcaption>{html.escape(caption)}</figcaption></figure>")

    s = d.summary
    rows_html = "".join(f"<tr><td>{html.escape(k)}</td><td>{v.get('seconds', 0):.1f}</td>"
                        f"<td>{html.escape(_describe(k, v))}</td></tr>" for k, v in s.items())
    body = [
        "<h1>GaussFluids demo report</h1>",
        f"<p>The built-in <code>water_sphere</code> scene: {gt.num_particles} simulated particles, "
        f"{len(times)} frames at {gt.fps:g} fps, rendered with Blender in {len(train.views)} training views and "
        f"{len(test.views)} held-out view; reconstructed from the first {len(clip)} frames, then predicted. "
        f"Every figure below was made by this run (folder <code>{html.escape(str(out))}</code>).</p>",
        f"<table><tr><th>stage</th><th>seconds</th><th>result</th></tr>{rows_html}</table>",
        "<h2>Animated preview</h2>", fig(gif, "held-out view: Blender truth (left) and the reconstruction (right); "
                                              "past the reconstructed clip, the PBF prediction"),
        "<h2>Input frames</h2>", fig(images["input"], "training views (columns) at the first, middle and last "
                                                      "reconstructed frame (rows)"),
        "<h2>Novel view</h2>", fig(images["heldout"], "held-out camera: Blender truth (top), reconstruction (bottom)"),
        "<h2>Particles</h2>", fig(images["particles"], "reconstructed (blue) and true (orange) particles at three "
                                                       "times; bottom row: the half nearer the camera removed, "
                                                       "showing the interior"),
        "<h2>Restyled in Blender</h2>",
        "".join(fig(p, f"the reconstruction through the Blender extension, look '{p.stem[5:]}'") for p in looks),
    ]
    if "prediction" in images:
        body += ["<h2>Prediction</h2>", fig(images["prediction"], "frames after the reconstructed clip: truth (top), "
                                                                 "simulated continuation with the learned "
                                                                 "appearance (bottom)")]
    body += ["<h2>Editing</h2>", fig(images["edit"], "half the particles removed, then simulated on"),
             "<h2>Plots</h2>", "".join(fig(p, p.stem.replace("_", " ")) for p in plots if p.exists())]
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>GaussFluids demo</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
            "img{max-width:100%;min-width:320px;image-rendering:pixelated}figure{margin:1em 0;display:inline-block}"
            "figcaption{color:#555;font-size:90%}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:4px 8px;text-align:left}</style></head><body>"
            + "\n".join(body) + "</body></html>")
    from gf_core.formats.hdf5 import atomic_write_text

    atomic_write_text(out / "report.html", page)
    return out / "report.html"


def _describe(stage: str, v: dict) -> str:
    items = [f"{k.replace('_', ' ')}: {x:.4g}" if isinstance(x, float) else f"{k.replace('_', ' ')}: {x}"
             for k, x in v.items() if k != "seconds" and x is not None]
    return "; ".join(items)
