"""Render a reconstruction with the Blender extension in two looks (the README's pictures).

    python render_data/showcase.py ZIP RUN/recon.h5 DATASET OUT_DIR [--time 0.5] [--res 400] [--samples 64]

Runs under the bpy module: installs the extension zip as a user does, builds the dataset
renderer's world, tank and the dataset's held-out camera (render_data/scene_builder), imports the
reconstruction, and renders one time in the 'water' and 'pink' looks to OUT_DIR/look_<preset>.png.
"""

import argparse
import json
import math
import sys
from pathlib import Path


def main(argv):
    p = argparse.ArgumentParser()
    p.add_argument("zip")
    p.add_argument("recon")
    p.add_argument("dataset")
    p.add_argument("out")
    p.add_argument("--time", type=float, default=0.5, help="seconds into the reconstruction")
    p.add_argument("--res", type=int, default=400)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--looks", default="water,pink")
    p.add_argument("--fps", type=float, default=30.0, help="scene frame rate the time maps onto")
    a = p.parse_args(argv)
    import bpy
    from mathutils import Matrix

    r = bpy.ops.extensions.package_install_files(filepath=a.zip, repo="user_default", enable_on_install=True)
    assert r == {"FINISHED"}
    from bl_ext.user_default.gaussfluids.render_data import scene_builder as sb

    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    meta = json.loads((Path(a.dataset) / "transforms_test.json").read_text())
    lo, hi = meta["scene_box"]
    sb.configure_render(resolution=a.res, samples=a.samples, seed=0, denoise=False)
    sb.build_world()
    sb.build_container(lo, hi, show=False)  # as the datasets: only reflections of the tank
    cam = sb.make_camera("showcase", Matrix(meta["frames"][0]["transform_matrix"]),
                         math.degrees(meta["camera_angle_x"]))
    sc = bpy.context.scene
    sc.camera = cam
    sc.render.film_transparent = False  # show the world, unlike the training images
    fps = int(round(a.fps))
    sc.render.fps = fps
    sc.frame_start = 1
    bpy.ops.import_scene.gaussfluids(filepath=a.recon, preset="water", fps=fps, start_frame=1)
    obj = next(o for o in sc.objects if o.type == "POINTCLOUD")
    frame = 1 + a.time * fps
    sc.frame_set(int(frame), subframe=frame - int(frame))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for look in a.looks.split(","):
        obj.gaussfluids.preset = look
        sc.render.filepath = str(out / f"look_{look}.png")
        bpy.ops.render.render(write_still=True)
        print("wrote", sc.render.filepath)


if __name__ == "__main__":
    main(sys.argv[1:])
