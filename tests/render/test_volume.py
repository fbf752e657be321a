"""Ray-marched images of a density grid: where a blob of smoke projects, and nothing outside it."""

import numpy as np

from gf_core.camera import Camera
from gf_core.render.volume import light_transmittance, render_density


def test_a_dense_blob_lands_where_its_centre_projects():
    n, lo, hi = 40, np.array([-0.2, -0.2, 0.0]), np.array([0.2, 0.2, 0.4])
    c = lo + (hi - lo) * np.array([0.6, 0.45, 0.3])
    axes = [lo[a] + (np.arange(n) + 0.5) * (hi[a] - lo[a]) / n for a in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    d = np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / (2 * 0.02 ** 2)).astype(np.float32)
    cam = Camera.look_at(np.array([0.3, -1.2, 0.5]), np.array([0.0, 0.0, 0.2]), np.array([0.0, 0.0, 1.0]),
                         fx=70.0, width=64, height=48)
    img = render_density(d, lo, hi, cam, ambient=1.0, light=0.0)
    (u, v), _ = cam.project(c)
    ys, xs = np.mgrid[0:48, 0:64]
    w = img / img.sum()
    assert abs((w * (xs + 0.5)).sum() - u) < 0.3 and abs((w * (ys + 0.5)).sum() - v) < 0.3
    assert img.max() > 0.3 and img[np.hypot(xs + 0.5 - u, ys + 0.5 - v) > 15].max() < 1e-3
    empty = render_density(np.zeros_like(d), lo, hi, cam)
    assert empty.max() == 0


def test_smoke_shades_what_lies_below_it():
    d = np.zeros((4, 4, 10), np.float32)
    d[:, :, 6:] = 1.0
    t = light_transmittance(__import__("torch").as_tensor(d), 0.01, 60.0).numpy()
    assert np.all(np.diff(t[1, 1], axis=0) >= 0) and t[1, 1, 0] < 0.2 and t[1, 1, 9] > 0.7


def test_held_out_cameras_sit_between_the_training_ones():
    from gf_core.formats.hdf5 import GridData
    from gf_core.render.volume import volume_rig

    g = GridData(density=np.zeros((1, 4, 4, 4), np.float32), times=np.zeros(1), domain_min=(-0.2, -0.2, 0.0),
                 domain_max=(0.2, 0.2, 0.6), fps=30.0)
    for views, tests in ((5, 1), (5, 4), (3, 2), (4, 1)):
        train, test = volume_rig(g, views=views, test_views=tests, resolution=32, fov_deg=40.0, arc_deg=90.0,
                                 elevation_deg=25.0, test_elevation_deg=None)
        azimuth = lambda c: np.degrees(np.arctan2(c.center[0], -c.center[1]))  # noqa: E731  (0 = front)
        a_train = sorted(azimuth(c) for c in train)
        assert np.allclose(a_train, np.linspace(-45, 45, views), atol=1e-6)
        step = 90.0 / (views - 1)
        for k, c in enumerate(test):  # halfway between training cameras k and k + 1, none on a training one
            assert abs(azimuth(c) - (-45 + step * (k + 0.5))) < 1e-6
            assert min(np.linalg.norm(c.center - t.center) for t in train) > 0.1
