"""Where a run starts: the floor seen in the masks when no scene box or floor is given."""

import math

import numpy as np
import pytest
import torch

from gf_core.camera import Camera, frontal_arc
from gf_core.recon.initial import box_from_cameras, estimate_floor, lowest_edge_points
from gf_core.recon.views import Views

RES = 96


def rig(height=0.5, n=5, arc=100.0):
    fx = 0.5 * RES / math.tan(math.radians(25.0))
    return frontal_arc(n, radius=1.6, target=(0.0, 0.0, 0.15), height=height, arc_degrees=arc, fx=fx,
                       width=RES, height_px=RES)


def mask(cam: Camera, inside) -> torch.Tensor:
    """Alpha of a solid given by ``inside(ray origins, directions) -> hit (M,)``, one ray per pixel."""
    u, v = np.meshgrid(np.arange(RES) + 0.5, np.arange(RES) + 0.5)
    d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
    d = d @ cam.camera_to_world[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return torch.as_tensor(inside(cam.center, d).reshape(RES, RES).astype(np.float32))


def box_solid(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)

    def hit(o, d):
        with np.errstate(divide="ignore"):
            t0, t1 = (lo - o) / d, (hi - o) / d
        return np.minimum(t0, t1).max(1) < np.maximum(t0, t1).min(1)
    return hit


def ball_solid(c, r):
    c = np.asarray(c, float)

    def hit(o, d):
        oc = o - c
        b = d @ oc
        return b * b - (oc @ oc - r * r) > 0
    return hit


def views_of(frames, cams) -> Views:
    """Training views of ``frames`` (one solid per frame) seen by ``cams``, 10 frames a second."""
    alphas, cameras, times, ids = [], [], [], []
    for k, solid in enumerate(frames):
        for j, cam in enumerate(cams):
            alphas.append(mask(cam, solid))
            cameras.append(cam)
            times.append(k / 10.0)
            ids.append(j)
    images = [torch.zeros(RES, RES, 3) for _ in alphas]
    return Views(images, alphas, cameras, np.asarray(times), ids, torch.zeros(3), 3)


def test_the_floor_under_fluid_at_rest_is_found_from_the_lowest_edges_of_the_masks():
    cams = rig()
    # a drop that falls onto a floor at z = 0.1 and lies there as a pool for the rest of the clip
    frames = [ball_solid((0, 0, 0.45 - 0.08 * k), 0.08) for k in range(3)]
    frames += [box_solid((-0.25, -0.2, 0.1), (0.2, 0.25, 0.16))] * 5
    v = views_of(frames, cams)
    lo, hi = box_from_cameras(cams)
    z = estimate_floor(v, lo, hi)
    pixel = 1.6 / cams[0].fx
    assert z == pytest.approx(0.1, abs=2 * pixel)
    # the lowest edge of one pool frame: every point on the floor's level, none far below it
    E = lowest_edge_points([(c, a) for c, a in zip(v.cameras[-5:], v.alphas[-5:])], lo, hi)
    assert len(E) > 50 and np.quantile(E[:, 2], 0.2) == pytest.approx(0.1, abs=2 * pixel)


def test_fluid_that_never_rests_gives_no_floor():
    cams = rig()
    falling = [ball_solid((0.02 * k, 0, 0.5 - 0.05 * k), 0.08) for k in range(8)]
    v = views_of(falling, cams)
    lo, hi = box_from_cameras(cams)
    assert estimate_floor(v, lo, hi) is None


def test_views_that_do_not_look_down_give_no_floor():
    cams = rig(height=-0.5)  # below the fluid, looking up at it
    v = views_of([box_solid((-0.25, -0.2, 0.1), (0.2, 0.25, 0.16))] * 5, cams)
    lo, hi = box_from_cameras(cams)
    assert len(lowest_edge_points(list(zip(v.cameras[:5], v.alphas[:5])), lo, hi)) == 0
    assert estimate_floor(v, lo, hi) is None


def test_a_rolled_camera_finds_the_same_floor():
    cams = rig()
    rolled = []
    for c in cams:  # each image turned a quarter: world down runs along the image's columns
        R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        w2c = c.world_to_camera.copy()
        w2c[:3] = R @ w2c[:3]
        rolled.append(Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, w2c))
    v = views_of([box_solid((-0.25, -0.2, 0.1), (0.2, 0.25, 0.16))] * 5, rolled)
    lo, hi = box_from_cameras(rolled)
    assert estimate_floor(v, lo, hi) == pytest.approx(0.1, abs=2 * 1.6 / cams[0].fx)


def test_a_run_without_a_scene_box_takes_the_floor_it_sees(tmp_path):
    """A pool at rest on a floor at z = 0 (the toolkit's splatting renderer, no scene box in the
    files): the run's box gets the floor seen in the masks, says so, and keeps particles above it."""
    import json

    from gf_core.data import load_dataset
    from gf_core.formats.hdf5 import SimData
    from gf_core.recon.trainer import Trainer
    from gf_core.synthetic import splat_dataset
    from helpers import quick_config

    s = 0.05
    g = np.arange(-0.2, 0.2 + 1e-9, s)
    X, Y, Z = np.meshgrid(g, g, [0.5 * s, 1.5 * s], indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    sim = SimData(positions=np.repeat(P[None], 5, 0).astype(np.float32), velocities=np.zeros((5, len(P), 3), np.float32),
                  fps=10.0, particle_radius=s / 2, scene="pool", domain_min=(-0.4, -0.4, 0.0),
                  domain_max=(0.4, 0.4, 0.8), solver="none", gravity=(0.0, 0.0, -9.81))
    root = splat_dataset(tmp_path / "pool", sim, resolution=96)
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        meta.pop("scene_box")
        p.write_text(json.dumps(meta))
    said = []
    tr = Trainer(quick_config(), load_dataset(root), out=tmp_path / "run", log=said.append)
    tr.initialise()
    assert tr.box_source == "cameras, floor from the silhouettes"
    assert any("from the masks' lowest edges" in m and "--floor" in m for m in said)
    spacing = tr.ctx.spacing
    assert tr.model.bounds.lo[2] == pytest.approx(0.5 * spacing, abs=0.5 * s)  # centres half a spacing up
    assert tr.ctx.has("floor")


def test_smoke_starts_inside_the_hull_of_its_bright_pixels(tmp_path):
    """Smoke on black has no alpha: init = "bright" carves from the pixels brighter than the
    background, so the start lies where the true density is (half of it, from four views over 90
    degrees); a random start almost never does."""
    from gf_core.data import load_dataset
    from gf_core.data.writers import write_smoke_dataset
    from gf_core.formats.hdf5 import write_grid
    from gf_core.recon.config import make_config
    from gf_core.recon.trainer import Trainer
    from gf_core.sim.smoke import PlumeConfig, simulate_plume

    g = simulate_plume(PlumeConfig(cells=20, seconds=0.6, fps=10))
    write_grid(tmp_path / "plume.h5", g)
    ds = write_smoke_dataset(tmp_path / "plume.h5", tmp_path / "ds", views=4, test_views=0, resolution=48,
                             frames=slice(3, 7), log=lambda *a: None)
    truth = g.density[3]
    lo, cell = np.asarray(g.domain_min), g.cell

    def share_in_smoke(init):
        cfg = make_config("smoke", overrides={"model": {"init": init, "init_particles": 500, "max_particles": 1000}})
        tr = Trainer(cfg, load_dataset(ds, grayscale=True), out=tmp_path / init, log=lambda *a: None)
        tr.initialise()
        idx = np.floor((tr.model.means.detach().numpy() - lo) / cell).astype(int)
        idx = np.clip(idx, 0, np.array(truth.shape) - 1)
        return float((truth[idx[:, 0], idx[:, 1], idx[:, 2]] > 0.02).mean()), tr.volume

    bright, v_bright = share_in_smoke("bright")
    rand, v_rand = share_in_smoke("random")
    # four views over 90 degrees: the hull is longer than the smoke along the views' directions
    assert bright > 0.4 and rand < 0.05 and v_bright < 0.05 * v_rand
