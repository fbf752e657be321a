"""Drives the Blender extension under the bpy module, for tests/blender/test_blender_addon.py.

    python tests/blender/addon_driver.py JOB.json

JOB: {"zip", "recon", "out", "steps": [...]}. Installs the zip the way a user does
(``extensions.package_install_files``), then runs the steps and writes OUT/result.json plus npz/png
files. A separate process per job: bpy is imported once per process, and the user-extension folder
lives under a private HOME.
"""

import json
import sys
from pathlib import Path

import numpy as np


def install(zip_path):
    import bpy

    r = bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default", enable_on_install=True)
    assert r == {"FINISHED"}, r
    assert "bl_ext.user_default.gaussfluids" in bpy.context.preferences.addons.keys()


def positions(obj):
    pc = obj.data
    p = np.empty(len(pc.points) * 3, np.float32)
    pc.attributes["position"].data.foreach_get("vector", p)
    return p.reshape(-1, 3)


def attr(obj, name, width):
    pc = obj.data
    a = np.empty(len(pc.points) * width, np.float32)
    pc.attributes[name].data.foreach_get({3: "vector", 4: "color"}.get(width, "value"), a)
    return a.reshape(-1, width) if width > 1 else a


def setup_render(bpy, res=32, samples=4):
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = samples
    sc.cycles.use_denoising = False
    sc.render.resolution_x = sc.render.resolution_y = res
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGB"
    sc.render.film_transparent = False


def main():
    job = json.loads(Path(sys.argv[1]).read_text())
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    import bpy

    install(job["zip"])
    res = {"blender_version": bpy.app.version_string}
    for step in job["steps"]:
        kind = step["do"]
        if kind == "import":
            for o in list(bpy.data.objects):  # the startup scene's cube, light, camera
                bpy.data.objects.remove(o)
            sc = bpy.context.scene
            sc.render.fps = step.get("fps", 24)
            sc.frame_start, sc.frame_end = 1, step.get("frame_end", 10)
            sc.frame_set(1)
            r = bpy.ops.import_scene.gaussfluids(filepath=job["recon"], preset=step.get("preset", "water"),
                                                 radius_scale=step.get("radius_scale", 1.5))
            res["import"] = list(r)
            obj = bpy.context.scene.objects[-1]
            res["object"] = obj.name
            res["type"] = obj.type
            res["lock_interface"] = bool(sc.render.use_lock_interface)
        elif kind == "frames":
            obj = bpy.context.scene.objects[res["object"]]
            data = {}
            for f in step["frames"]:
                whole = int(np.floor(f))
                bpy.context.scene.frame_set(whole, subframe=f - whole)
                data[f"p_{f}"] = positions(obj)
                data[f"v_{f}"] = attr(obj, "velocity", 3)
                data[f"r_{f}"] = attr(obj, "radius", 1)
                data[f"c_{f}"] = attr(obj, "gf_color", 4)
            np.savez(out / "frames.npz", **data)
            s = obj.gaussfluids
            res["mapping"] = {"fps": s.fps, "start_frame": s.start_frame, "speed": s.speed}
        elif kind == "render":
            obj = bpy.context.scene.objects[res["object"]]
            setup_render(bpy, step.get("res", 32), step.get("samples", 4))
            sc = bpy.context.scene
            if sc.camera is None:
                from mathutils import Matrix  # noqa: F401

                cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
                sc.collection.objects.link(cam)
                cam.location = step["camera"]["eye"]
                import mathutils

                d = mathutils.Vector(step["camera"]["target"]) - cam.location
                cam.rotation_euler = d.to_track_quat("-Z", "Y").to_euler()
                sc.camera = cam
                light = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
                light.data.energy = 3.0
                sc.collection.objects.link(light)
                world = bpy.data.worlds.new("w")
                world.use_nodes = True
                world.node_tree.nodes["Background"].inputs[0].default_value = (0.3, 0.3, 0.3, 1)
                sc.world = world
            obj.gaussfluids.preset = step["preset"]
            for f in step["frames"]:
                sc.frame_set(f)
                sc.render.filepath = str(out / f"{step['preset']}_{f}.png")
                bpy.ops.render.render(write_still=True)
        elif kind == "bake_usd":
            obj = bpy.context.scene.objects[res["object"]]
            bpy.context.view_layer.objects.active = obj
            from bl_ext.user_default.gaussfluids import bake

            frames = bake.frame_samples(bpy.context.scene.frame_start, bpy.context.scene.frame_end,
                                        step.get("substeps", 1))
            got = {}
            for f in frames:
                whole = int(np.floor(f))
                bpy.context.scene.frame_set(whole, subframe=f - whole)
                got[f"live_{f}"] = positions(obj)
            r = bpy.ops.gaussfluids.bake_usd(filepath=str(out / "cache.usdc"), substeps=step.get("substeps", 1),
                                             replace=step.get("replace", False))
            res["bake_usd"] = list(r)
            for f in frames:
                got[f"usd_{f}"] = bake.read_usd_points(str(out / "cache.usdc"), f)
            np.savez(out / "usd.npz", **got)
            res["usd_frames"] = frames
            res["live_after_replace"] = bool(obj.gaussfluids.live)
            if step.get("replace"):
                imported = [o for o in bpy.context.scene.objects if o.name != res["object"] and o.type == "POINTCLOUD"]
                res["usd_objects"] = [o.name for o in imported]
                data = {}
                for f in (2, 5):
                    bpy.context.scene.frame_set(f)
                    ev = imported[0].evaluated_get(bpy.context.evaluated_depsgraph_get())
                    p = np.empty(len(ev.data.points) * 3, np.float32)
                    ev.data.attributes["position"].data.foreach_get("vector", p)
                    mw = np.asarray(ev.matrix_world)
                    data[f"imported_{f}"] = p.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]
                np.savez(out / "usd_imported.npz", **data)
        elif kind == "bake_vdb":
            obj = bpy.context.scene.objects[res["object"]]
            bpy.context.view_layer.objects.active = obj
            r = bpy.ops.gaussfluids.bake_vdb(directory=str(out / "vdb"), frame_start=1, frame_end=2)
            res["bake_vdb"] = list(r)
            from bl_ext.user_default.gaussfluids import bake

            vdb = bake.bundled_module("openvdb")
            files = sorted((out / "vdb").glob("*.vdb"))
            res["vdb_files"] = [f.name for f in files]
            grid = vdb.read(str(files[0]), "density")
            lo, hi = grid.evalActiveVoxelBoundingBox()
            res["vdb_active"] = grid.activeVoxelCount()
            res["vdb_minmax"] = list(grid.evalMinMax())
            # world position of the active bounding box's centre
            c = [(a + b) / 2 for a, b in zip(lo, hi)]
            res["vdb_centre"] = list(grid.transform.indexToWorld(c))
        elif kind == "volume_import":
            # an exported OpenVDB file through Blender's own import, rendered alone in the smoke material
            from bl_ext.user_default.gaussfluids.render_data import scene_builder
            from mathutils import Vector

            sc = bpy.context.scene
            recon_obj = sc.objects[res["object"]]
            recon_obj.hide_render = True
            path = Path(step["path"])
            before = set(bpy.data.objects)
            r = bpy.ops.object.volume_import(filepath=str(path), directory=str(path.parent), files=[{"name": path.name}])
            res["volume_import"] = list(r)
            vol = next(o for o in bpy.data.objects if o not in before)
            vol.data.grids.load()
            res["volume_grids"] = [g.name for g in vol.data.grids]
            corners = np.array([vol.matrix_world @ Vector(c) for c in vol.bound_box])
            res["volume_bounds"] = [corners.min(0).tolist(), corners.max(0).tolist()]
            vol.data.materials.append(scene_builder.make_material("smoke"))
            sc.frame_set(step["frame"])
            sc.render.filepath = str(out / "vdb_import.png")
            bpy.ops.render.render(write_still=True)
            bpy.data.objects.remove(vol)
            recon_obj.hide_render = False
        elif kind == "import_bad":
            try:
                r = bpy.ops.import_scene.gaussfluids(filepath=step["path"])
                res["bad"] = list(r)
            except RuntimeError as e:  # an operator's error report, raised in background mode
                res["bad"] = str(e)
        elif kind == "save":
            bpy.ops.wm.save_as_mainfile(filepath=str(out / "scene.blend"))
        elif kind == "open_and_render":
            # what `blender -b scene.blend -a` does: open the file, render the frame range
            bpy.ops.wm.open_mainfile(filepath=step["blend"])
            sc = bpy.context.scene
            obj = sc.objects[step["object"]]
            data = {}
            for f in step["frames"]:
                sc.frame_set(f)
                data[f"p_{f}"] = positions(obj)
            np.savez(out / "reopened.npz", **data)
            sc.frame_start, sc.frame_end = step["frames"][0], step["frames"][-1]
            sc.render.filepath = str(out / "anim_####")
            bpy.ops.render.render(animation=True)
        elif kind == "dataset":
            r = bpy.ops.gaussfluids.render_dataset(sim=step["sim"], out=str(out / "dataset"), views=1, test_views=1,
                                                   resolution=16, samples=1, frames="0:2")
            res["dataset"] = list(r)
        else:
            raise ValueError(kind)
    (out / "result.json").write_text(json.dumps(res))


if __name__ == "__main__":
    main()
