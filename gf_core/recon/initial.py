"""Where the particles start: the scene box, and the visual hull carved from alpha masks.

Scene box, in order: the config's ``model.scene_box`` (``gf-cli reconstruct --scene-box``); the
dataset's ``scene_box`` (written by ``gf-cli render-dataset``: the simulation's domain); else
derived from the cameras: the point nearest to every optical axis (least squares) with a
half-size of the smallest half-width that any camera sees at that distance. A floor height alone
(``model.floor``, ``--floor``, or a dataset's ``floor``: a tank or a table whose walls are not
known) replaces the box's lowest z; the box's own floor is known only when the box is given.
Without either, the floor is estimated from the masks (``estimate_floor``, ``model.floor_estimate``).

Carving (space carving, Kutulakos & Seitz 2000): candidate points drawn uniformly in the box are
kept when they project onto alpha >= threshold in every view that sees them (and at least one
view sees them). The surviving fraction also estimates the fluid's volume, from which the
particle spacing follows: spacing = (V / N)^(1/3).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..camera import Camera
from ..errors import InputError

if TYPE_CHECKING:
    from .model import FluidModel


def box_from_cameras(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    if not cameras:
        raise InputError("scene box", "no cameras to derive a scene box from")
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        o = c.center
        d = c.camera_to_world[:3, 2]  # OpenCV: +z looks forward
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    if np.linalg.matrix_rank(A) < 3:  # one camera, or parallel axes: a point 1 focal distance ahead
        c = cameras[0]
        centre = c.center + c.camera_to_world[:3, 2] * np.linalg.norm(c.center)
    else:
        centre = np.linalg.solve(A, b)
    half = min(np.linalg.norm(centre - c.center) * 0.5 * min(c.width / c.fx, c.height / c.fy) for c in cameras)
    return centre - half, centre + half


def scene_box(cfg_box, dataset, cameras: list[Camera], cfg_floor=()) -> tuple[np.ndarray, np.ndarray, str]:
    """(lo, hi, source) of the scene box. ``source`` is "config", "dataset", "cameras" (no floor
    known) or "cameras, floor from config|dataset"."""
    for box, src in ((cfg_box, "config"), (dataset.meta.get("scene_box"), "dataset")):
        if box:
            a = np.asarray(box, np.float64)
            if a.shape != (2, 3) or not np.all(np.isfinite(a)) or np.any(a[1] <= a[0]):
                raise InputError(src, f"scene_box must be [[x0, y0, z0], [x1, y1, z1]] with x1 > x0 ..., got {box}")
            return a[0], a[1], src
    lo, hi = box_from_cameras(cameras)
    for floor, src in ((list(cfg_floor or ()), "config"), ([dataset.meta["floor"]] if "floor" in dataset.meta else [], "dataset")):
        if floor:
            z = float(floor[0])
            if z >= hi[2]:
                raise InputError(f"floor ({src})", f"the floor z = {z:g} m lies above the cameras' view of the "
                                                   f"scene (which ends at z = {hi[2]:.3g} m)")
            return np.array([lo[0], lo[1], z]), hi, f"cameras, floor from {src}"
    return lo, hi, "cameras"


def lowest_edge_points(views: list[tuple[Camera, torch.Tensor]], lo, hi, *, threshold: float = 0.5,
                       steps: int = 384, max_rays: int = 128) -> np.ndarray:
    """(M, 3) points where the fluid of one frame, seen in its masks ``views`` [(camera, alpha)],
    has its lowest edge (gravity along -z).

    A view that looks down at fluid resting on a floor sees the fluid's lowest edge where it
    touches the floor on its near side, and the ray through that edge enters the visual hull there:
    the other views fix where the fluid begins along it. For every image column (at most
    ``max_rays`` per view, the image's own "down" taken as the direction of world -z) the ray
    through the silhouette's lowest pixel is marched through the box ``lo``..``hi`` in ``steps``
    samples, and the point where it first enters the hull is kept. Views whose optical axis does not
    point down are skipped."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    entry = []
    for cam, alpha in views:
        a = alpha.detach().cpu().numpy() if isinstance(alpha, torch.Tensor) else np.asarray(alpha)
        c2w = cam.camera_to_world
        if c2w[2, 2] >= 0.0:
            continue
        uv0, _ = cam.project(0.5 * (lo + hi))
        uv1, _ = cam.project(0.5 * (lo + hi) - np.array([0.0, 0.0, 0.01 * float(np.linalg.norm(hi - lo))]))
        down = (uv1 - uv0).ravel()
        if not np.all(np.isfinite(down)):
            continue
        m = a >= threshold
        if abs(down[1]) >= abs(down[0]):   # world down runs along the image's rows
            cols = np.flatnonzero(m.any(0))
            if not len(cols):
                continue
            cols = cols[np.linspace(0, len(cols) - 1, min(len(cols), max_rays)).round().astype(int)]
            sub = m[:, cols]
            rows = (sub.shape[0] - 1 - np.argmax(sub[::-1], 0)) if down[1] > 0 else np.argmax(sub, 0)
        else:                              # along its columns
            rows = np.flatnonzero(m.any(1))
            if not len(rows):
                continue
            rows = rows[np.linspace(0, len(rows) - 1, min(len(rows), max_rays)).round().astype(int)]
            sub = m[rows, :]
            cols = (sub.shape[1] - 1 - np.argmax(sub[:, ::-1], 1)) if down[0] > 0 else np.argmax(sub, 1)
        d = np.stack([(cols + 0.5 - cam.cx) / cam.fx, (rows + 0.5 - cam.cy) / cam.fy, np.ones(len(cols))], 1) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = cam.center
        with np.errstate(divide="ignore", invalid="ignore"):  # the part of each ray inside the box (slabs)
            t0, t1 = (lo - o) / d, (hi - o) / d
        t_near = np.nanmax(np.minimum(t0, t1), 1).clip(min=0.0)
        t_far = np.nanmin(np.maximum(t0, t1), 1)
        ok = t_far > t_near
        if not ok.any():
            continue
        d, t_near, t_far = d[ok], t_near[ok], t_far[ok]
        s = t_near[:, None] + (t_far - t_near)[:, None] * (np.arange(steps) + 0.5)[None, :] / steps
        P = o + d[:, None, :] * s[..., None]
        inside = in_hull(P.reshape(-1, 3), views, threshold).reshape(P.shape[:2])
        hit = inside.any(1)
        entry.append(P[np.flatnonzero(hit), inside.argmax(1)[hit]])
    return np.concatenate(entry) if entry else np.zeros((0, 3))


def estimate_floor(views, lo, hi, *, threshold: float = 0.5, max_frames: int = 30, quantile: float = 0.2,
                   tolerance: float = 0.02, min_frames: int = 3) -> float | None:
    """The floor of a clip from its masks, or None: a frame's lowest edge (``lowest_edge_points``)
    is at the ``quantile`` of its points' heights (a few rays enter the hull low where no view fixes
    the fluid's extent); fluid at rest on a floor keeps that height from frame to frame, falling
    fluid does not. So the floor is the median lowest edge of the frames whose lowest edge lies
    within ``tolerance`` x the box's height of the lowest one, when there are at least
    ``min_frames`` (and a tenth of the frames) of them; None otherwise, without alpha, or when no
    view looks down. At most ``max_frames`` frames spread over the clip are looked at."""
    times = views.unique_times
    times = times[np.unique(np.linspace(0, len(times) - 1, min(len(times), max_frames)).round().astype(int))]
    edges = []
    for t in times:
        idx = views.at_time(t)
        if not idx or any(views.alphas[i] is None for i in idx):
            continue
        E = lowest_edge_points([(views.cameras[i], views.alphas[i]) for i in idx], lo, hi, threshold=threshold)
        if len(E) >= 8:
            edges.append(float(np.quantile(E[:, 2], quantile)))
    if not edges:
        return None
    z = np.asarray(edges)
    near = z[z <= z.min() + tolerance * float(hi[2] - lo[2])]
    return float(np.median(near)) if len(near) >= max(min_frames, 0.1 * len(times)) else None


def floor_known(source: str) -> bool:
    """Whether a scene box of ``source`` (``scene_box``) has a real floor: a given box, or a floor
    given alone; not a box guessed from the cameras."""
    return source in ("config", "dataset") or "floor from" in source


def walls_known(source: str) -> bool:
    """Whether a scene box of ``source`` (``scene_box``) is the real container, walls and all: a box
    given in the config or the dataset; not one guessed from the cameras (with or without a floor)."""
    return source in ("config", "dataset")


def in_hull(P: np.ndarray, views: list[tuple[Camera, torch.Tensor]], threshold: float = 0.5) -> np.ndarray:
    """(M,) bool: which points P (M, 3) are inside the visual hull of the masks ``views``
    [(camera, alpha (H, W))]: seen by at least one view, and on the fluid (alpha >= threshold) in
    every view that sees them."""
    inside = np.ones(len(P), bool)
    seen = np.zeros(len(P), bool)
    for cam, alpha in views:
        a = alpha.detach().cpu().numpy() if isinstance(alpha, torch.Tensor) else np.asarray(alpha)
        uv, z = cam.project(P)
        ok = (z > cam.near) & np.isfinite(uv).all(-1)
        col = np.floor(np.nan_to_num(uv[:, 0], nan=-1)).astype(np.int64)
        row = np.floor(np.nan_to_num(uv[:, 1], nan=-1)).astype(np.int64)
        ok &= (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        seen |= ok
        val = np.zeros(len(P))
        val[ok] = a[row[ok], col[ok]]
        inside &= ~ok | (val >= threshold)
    return inside & seen


def carve(lo, hi, views: list[tuple[Camera, torch.Tensor]], n: int, *, threshold: float = 0.5,
          seed: int = 0, max_candidates: int = 4_000_000, masks: str = "alpha masks") -> tuple[np.ndarray, float]:
    """``n`` points inside the visual hull of the masks ``views`` [(camera, alpha (H, W))], and
    the hull's volume estimate (m^3). Raises if every mask is empty."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    box_vol = float(np.prod(hi - lo))
    kept, tried = [], 0
    batch = max(20 * n, 200_000)
    while tried < max_candidates:
        P = lo + (hi - lo) * rng.random((batch, 3))
        tried += batch
        kept.append(P[in_hull(P, views, threshold)])
        if sum(k.shape[0] for k in kept) >= n:
            break
    pts = np.concatenate(kept, 0)
    if pts.shape[0] == 0:
        raise InputError("reconstruct", f"the {masks} of the canonical frame are empty in every view "
                                        "(nothing to reconstruct there): choose another canonical frame "
                                        "(decoder.canonical_time, 0 = first, 1 = last) or model.init = 'random'")
    volume = box_vol * pts.shape[0] / tried
    if pts.shape[0] < n:  # a thin hull: repeat points with a small jitter
        extra = pts[rng.integers(0, pts.shape[0], n - pts.shape[0])]
        jit = 0.25 * (volume / n) ** (1 / 3)
        pts = np.concatenate([pts, extra + rng.normal(scale=jit, size=extra.shape)], 0)
    else:
        pts = pts[rng.permutation(pts.shape[0])[:n]]
    return pts, volume


def bright_mask(image: torch.Tensor, background, threshold: float) -> torch.Tensor:
    """(H, W) 1 where an image (H, W, C) differs from the background colour by at least
    ``threshold`` in some channel (smoke on a dark background: its silhouette), else 0."""
    bg = torch.as_tensor(background, dtype=image.dtype, device=image.device).reshape(1, 1, -1)
    return ((image - bg).abs().amax(-1) >= threshold).to(image.dtype)


def spacing_for(volume: float, n: int) -> float:
    return (max(volume, 1e-30) / max(n, 1)) ** (1.0 / 3.0)


def random_in_box(lo, hi, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return lo + (hi - lo) * rng.random((n, 3))


def mean_foreground_color(samples, channels: int) -> np.ndarray:
    """Mean colour where alpha > 0.5 over the given samples (grey 0.5 without alpha)."""
    acc, cnt = np.zeros(channels), 0
    for img, alpha in samples:
        if alpha is None:
            continue
        m = alpha > 0.5
        if m.any():
            acc += img[m].reshape(-1, channels).sum(0)
            cnt += int(m.sum())
    return acc / cnt if cnt else np.full(channels, 0.5)


@dataclass
class Start:
    """The particles a run starts from and the scene quantities fixed with them."""

    model: "FluidModel"
    volume: float        # m^3 the masks' hull (or the box) held
    spacing: float       # particle spacing (V / N)^(1/3)
    h: float             # the density loss's smoothing length
    box_source: str      # where the scene box came from (``scene_box``)
    init_source: str     # "carved" or "random"


def start(cfg, views, dataset, *, t_canon: float, time_map, decoder_cfg, knots, device, log=print) -> Start:
    """The canonical particles of a run: in the scene box (``scene_box``), carved from the
    canonical frame's masks (or uniform in the box without them), ``model.init_scale`` spacings
    wide, of the fluid's mean colour; with a decoder (``decoder_cfg``) unless the scene is static."""
    from .model import Bounds, FluidModel

    mc = cfg.model
    canon = views.at_time(t_canon)
    lo, hi, src = scene_box(mc.scene_box, dataset, [views.cameras[i] for i in canon], mc.floor)
    if not floor_known(src):
        z = estimate_floor(views, lo, hi, threshold=mc.carve_threshold) if mc.floor_estimate == "silhouettes" else None
        if z is not None and lo[2] < z < hi[2]:
            lo = np.array([lo[0], lo[1], z])
            src = "cameras, floor from the silhouettes"
            log(f"warning: no scene box and no floor are known (none given, none in the dataset): the box is "
                f"guessed from the cameras, and the floor, z = {z:.4g} m, from the masks' lowest edges "
                f"(model.floor_estimate). Nothing keeps particles inside the real container's walls. Give the "
                f"container with --scene-box=X0,Y0,Z0,X1,Y1,Z1 or its floor with --floor Z (metres, z up).")
        else:
            log("warning: no scene box and no floor are known (none given, none in the dataset, none seen in "
                "the masks), so the box is guessed from the cameras: nothing keeps particles inside the real "
                "container or above its floor (where no view can tell, they sink below it), and the floor "
                "and settle terms are off. Give the container with --scene-box=X0,Y0,Z0,X1,Y1,Z1 or at "
                "least its floor with --floor Z (metres, z up).")
    n0 = min(mc.init_particles, mc.max_particles)
    if mc.init == "carve" and all(views.alphas[i] is not None for i in canon):
        pts, volume = carve(lo, hi, [(views.cameras[i], views.alphas[i]) for i in canon], n0,
                            threshold=mc.carve_threshold, seed=cfg.train.seed)
        init_source = "carved"
    elif mc.init == "bright":
        masks = [(views.cameras[i], bright_mask(views.images[i], views.background, mc.bright_threshold)) for i in canon]
        pts, volume = carve(lo, hi, masks, n0, threshold=0.5, seed=cfg.train.seed,
                            masks=f"bright pixels (model.bright_threshold = {mc.bright_threshold:g})")
        init_source = "carved from the bright pixels"
    else:
        if mc.init == "carve":
            log("no alpha in the canonical frame's images: particles start uniform in the scene box")
        pts, volume = random_in_box(lo, hi, n0, cfg.train.seed), float(np.prod(hi - lo))
        init_source = "random"
    spacing = spacing_for(volume, n0)
    color = mean_foreground_color([(views.images[i].cpu().numpy(),
                                    None if views.alphas[i] is None else views.alphas[i].cpu().numpy())
                                   for i in canon], views.channels)
    # a fluid particle's centre lies half a spacing from the wall it rests on, as in the simulators
    # (model.wall_inset): clamped to the box's faces instead, a sheet on the floor sits half a
    # spacing too low (docs/experiments/2026-12-02-wall-inset.md)
    bounds = Bounds.for_box(lo, hi, spacing, mc.wall_inset * spacing)
    model = FluidModel.from_points(
        torch.as_tensor(pts, dtype=torch.float32, device=device), radius=mc.init_scale * spacing,
        color=color, opacity=mc.init_opacity, sh_degree=mc.sh_degree, channels=views.channels,
        bounds=bounds, time_map=time_map, decoder_cfg=decoder_cfg, knots=knots, seed=cfg.train.seed)
    log(f"start: {len(model)} particles ({init_source}) in the scene box from {src} "
        f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()}; fluid volume {volume:.3g} m^3, "
        f"spacing {spacing:.4g} m, h = {cfg.density.h_factor * spacing:.4g} m; "
        f"{'static scene (no decoder)' if decoder_cfg is None else f'{len(views.unique_times)} times'}")
    return Start(model, volume, spacing, cfg.density.h_factor * spacing, src, init_source)


__all__ = ["Start", "start", "bright_mask", "floor_known", "lowest_edge_points", "estimate_floor", "scene_box", "box_from_cameras", "carve", "spacing_for", "random_in_box", "mean_foreground_color"]
