"""Render a reconstruction with the Blender extension in its looks (the README's pictures).

    python render_data/showcase.py ZIP RUN/recon.h5 DATASET OUT_DIR [--time 0.5] [--res 400] [--samples 64]
        [--looks water,pink] [--vdb FILE] [--background GRAY] [--surface-radius S]

Runs under the bpy module: installs the extension zip as a user does, builds the dataset
renderer's world and tank (render_data/scene_builder) around the dataset's scene box and its
held-out camera (any layout gf_core reads: the camera comes from its loader), imports the
reconstruction, and renders one time in each look to OUT_DIR/look_<preset>.png. ``--vdb`` also
brings an OpenVDB density file (``gf-cli export --format vdb``) in through Blender's own volume
import, gives it the smoke material, and renders it alone to OUT_DIR/vdb_smoke.png.
``--background`` replaces the sky gradient with a uniform grey and a sun (smoke in a dark room).
"""

import argparse
import math
import sys
from pathlib import Path


def held_out_view(dataset: str, time: float, resolution: int):
    """(camera-to-world in Blender's convention, horizontal field of view in degrees, width, height,
    scene box or None, the view's image nearest ``time``, at most ``resolution`` pixels wide) of the
    dataset's first held-out view (its first training view without one)."""
    from gf_core.data import detect_layout, load_dataset
    from gf_core.errors import InputError

    try:
        detect_layout(Path(dataset), "test")
        split = "test"
    except InputError:
        split = "train"
    ds = load_dataset(dataset, split=split)
    view = ds.views[0]
    cam = ds.cameras()[view]
    t = min(ds.times, key=lambda x: abs(x - time))
    small = ds.resized(width=resolution) if resolution < cam.width else ds  # never upscaled
    img = small[small.indices(view_id=view, time=t)[0]].image
    return (cam.to_blender_c2w(), math.degrees(cam.camera_angle_x), cam.width, cam.height,
            ds.meta.get("scene_box"), img)


def uniform_world(bpy, gray: float):
    world = bpy.data.worlds.new("gf_showcase_world")
    bpy.context.scene.world = world
    if hasattr(world, "use_nodes") and not world.use_nodes:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (gray, gray, gray, 1.0)
    sun = bpy.data.objects.new("gf_sun", bpy.data.lights.new("gf_sun", "SUN"))
    sun.data.energy = 4.0
    sun.rotation_euler = (math.radians(40), math.radians(20), math.radians(30))
    bpy.context.scene.collection.objects.link(sun)


def import_vdb(bpy, path: Path, material):
    """The file through Blender's own OpenVDB import (File > Import > OpenVDB), with ``material``."""
    before = set(bpy.data.objects)
    r = bpy.ops.object.volume_import(filepath=str(path), directory=str(path.parent), files=[{"name": path.name}])
    if r != {"FINISHED"}:
        raise RuntimeError(f"Blender's volume import of {path} returned {r}")
    obj = next(o for o in bpy.data.objects if o not in before)
    obj.data.materials.clear()
    obj.data.materials.append(material)
    return obj


def main(argv):
    p = argparse.ArgumentParser()
    p.add_argument("zip")
    p.add_argument("recon")
    p.add_argument("dataset")
    p.add_argument("out")
    p.add_argument("--time", type=float, default=0.5, help="seconds into the reconstruction")
    p.add_argument("--res", type=int, default=400, help="image width in pixels (the height follows the camera)")
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--looks", default="water,pink")
    p.add_argument("--fps", type=float, default=30.0, help="scene frame rate the time maps onto")
    p.add_argument("--vdb", type=Path, default=None, help="an OpenVDB density file to render through Blender's import")
    p.add_argument("--surface-radius", type=float, default=None,
                   help="surface and smoke looks: sphere radius in particle spacings (default: the extension's)")
    p.add_argument("--background", type=float, default=None,
                   help="a uniform grey world (0..1) and a sun instead of the sky gradient; no tank")
    a = p.parse_args(argv)
    c2w, fov, width, height, box, image = held_out_view(a.dataset, a.time, a.res)
    from gf_core.data.images import write_png

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "heldout.png", image)
    import bpy
    from mathutils import Matrix

    r = bpy.ops.extensions.package_install_files(filepath=a.zip, repo="user_default", enable_on_install=True)
    assert r == {"FINISHED"}
    from bl_ext.user_default.gaussfluids.render_data import scene_builder as sb

    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    sb.configure_render(resolution=a.res, samples=a.samples, seed=0, denoise=False)
    sc = bpy.context.scene
    sc.render.resolution_y = max(1, round(a.res * height / width))
    if a.background is None:
        sb.build_world()
        if box is not None:
            sb.build_container(*box, show=False)  # as the datasets: only reflections of the tank
    else:
        uniform_world(bpy, a.background)
    cam = sb.make_camera("showcase", Matrix(c2w.tolist()), fov)
    sc.camera = cam
    sc.render.film_transparent = False  # show the world, unlike the training images
    fps = int(round(a.fps))
    sc.render.fps = fps
    sc.frame_start = 1
    bpy.ops.import_scene.gaussfluids(filepath=a.recon, preset="water", fps=fps, start_frame=1)
    obj = next(o for o in sc.objects if o.type == "POINTCLOUD")
    if a.surface_radius is not None:
        obj.gaussfluids.surface_radius = a.surface_radius
    frame = 1 + a.time * fps
    sc.frame_set(int(frame), subframe=frame - int(frame))
    for look in [s for s in a.looks.split(",") if s]:
        obj.gaussfluids.preset = look
        sc.render.filepath = str(out / f"look_{look}.png")
        bpy.ops.render.render(write_still=True)
        print("wrote", sc.render.filepath)
    if a.vdb is not None:
        obj.hide_render = True
        vol = import_vdb(bpy, a.vdb, sb.make_material("smoke"))
        sc.render.filepath = str(out / "vdb_smoke.png")
        bpy.ops.render.render(write_still=True)
        print("wrote", sc.render.filepath, "from", vol.name)


if __name__ == "__main__":
    main(sys.argv[1:])
