"""Operators: import a reconstruction, bake USD / OpenVDB, render a training dataset."""

import os
import subprocess
import sys

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper, ImportHelper

from . import animation, bake, presets


def _driven(context):
    obj = context.active_object
    if obj is None or obj.type != "POINTCLOUD" or not obj.gaussfluids.filepath:
        return None
    return obj


class GAUSSFLUIDS_OT_import(bpy.types.Operator, ImportHelper):
    """Import a GaussFluids reconstruction (recon.h5) as an animated point cloud"""

    bl_idname = "import_scene.gaussfluids"
    bl_label = "Import GaussFluids Reconstruction"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".h5"
    filter_glob: bpy.props.StringProperty(default="*.h5", options={"HIDDEN"})
    fps: bpy.props.FloatProperty(name="FPS", default=0.0, min=0.0,
                                 description="Frames per second of reconstruction time (0: the scene's)")
    start_frame: bpy.props.IntProperty(name="Start Frame", default=-1,
                                       description="Frame showing the first reconstructed time (-1: scene start)")
    speed: bpy.props.FloatProperty(name="Speed", default=1.0, description="Playback speed (0.5: slow motion)")
    radius_scale: bpy.props.FloatProperty(name="Radius Scale", default=1.5, min=1e-4,
                                          description="Point radius = this x the particle's Gaussian size")
    preset: bpy.props.EnumProperty(name="Look", items=presets.ENUM_ITEMS, default="water")
    velocity: bpy.props.BoolProperty(name="Velocity Attribute", default=True,
                                     description="Write 'velocity' (m/s) for motion blur")

    def execute(self, context):
        try:
            obj = animation.import_reconstruction(
                self.filepath, context, fps=self.fps or None,
                start_frame=None if self.start_frame < 0 else self.start_frame, speed=self.speed,
                radius_scale=self.radius_scale, preset=self.preset, velocity=self.velocity)
        except Exception as e:
            self.report({"ERROR"}, f"{self.filepath}: {e}" if self.filepath not in str(e) else str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"imported {len(obj.data.points)} particles as {obj.name}")
        return {"FINISHED"}


def _frames_and_times(context, obj, frame_start, frame_end, substeps):
    s = obj.gaussfluids
    frames = bake.frame_samples(frame_start, frame_end, substeps)
    return frames, [animation.scene_time(s, f) for f in frames]


class GAUSSFLUIDS_OT_bake_usd(bpy.types.Operator, ExportHelper):
    """Bake the active reconstruction to a USD points cache (renders without the handler, opens in other tools)"""

    bl_idname = "gaussfluids.bake_usd"
    bl_label = "Bake USD Cache"
    bl_options = {"REGISTER"}

    filename_ext = ".usdc"
    filter_glob: bpy.props.StringProperty(default="*.usd;*.usdc;*.usda", options={"HIDDEN"})
    frame_start: bpy.props.IntProperty(name="Start", default=-1, description="-1: the scene's start")
    frame_end: bpy.props.IntProperty(name="End", default=-1, description="-1: the scene's end")
    substeps: bpy.props.IntProperty(name="Sub-steps", default=1, min=1, max=64,
                                    description="Time samples per frame (motion blur, retiming)")
    replace: bpy.props.BoolProperty(name="Use the Cache", default=False,
                                    description="Import the baked cache and stop updating the live object")

    @classmethod
    def poll(cls, context):
        return _driven(context) is not None

    def execute(self, context):
        obj = _driven(context)
        sc = context.scene
        f0 = sc.frame_start if self.frame_start < 0 else self.frame_start
        f1 = sc.frame_end if self.frame_end < 0 else self.frame_end
        try:
            frames, times = _frames_and_times(context, obj, f0, f1, self.substeps)
            anim = animation.load_animation(obj.gaussfluids.filepath)
            path = bake.bake_usd(anim, bpy.path.abspath(self.filepath), frames, times,
                                 fps=sc.render.fps / sc.render.fps_base, radius_scale=obj.gaussfluids.radius_scale,
                                 velocity=obj.gaussfluids.velocity)
        except Exception as e:
            self.report({"ERROR"}, f"USD bake to {self.filepath} failed: {e}")
            return {"CANCELLED"}
        if self.replace:
            bpy.ops.wm.usd_import(filepath=path)
            obj.gaussfluids.live = False
            obj.hide_render = obj.hide_viewport = True
        self.report({"INFO"}, f"baked {len(frames)} time samples to {path}")
        return {"FINISHED"}


class GAUSSFLUIDS_OT_bake_vdb(bpy.types.Operator):
    """Bake the active reconstruction to OpenVDB density grids, one file per frame (smoke)"""

    bl_idname = "gaussfluids.bake_vdb"
    bl_label = "Bake OpenVDB Density"
    bl_options = {"REGISTER"}

    directory: bpy.props.StringProperty(name="Folder", subtype="DIR_PATH")
    voxel_size: bpy.props.FloatProperty(name="Voxel Size", default=0.0, min=0.0,
                                        description="0: half the median point radius")
    frame_start: bpy.props.IntProperty(name="Start", default=-1, description="-1: the scene's start")
    frame_end: bpy.props.IntProperty(name="End", default=-1, description="-1: the scene's end")

    @classmethod
    def poll(cls, context):
        return _driven(context) is not None

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        obj = _driven(context)
        sc = context.scene
        if not self.directory:
            self.report({"ERROR"}, "choose a folder for the OpenVDB files")
            return {"CANCELLED"}
        f0 = sc.frame_start if self.frame_start < 0 else self.frame_start
        f1 = sc.frame_end if self.frame_end < 0 else self.frame_end
        try:
            frames, times = _frames_and_times(context, obj, f0, f1, 1)
            anim = animation.load_animation(obj.gaussfluids.filepath)
            voxel = self.voxel_size
            if voxel <= 0:
                r = obj.gaussfluids.radius_scale * np.exp(anim.log_scales.mean(1))
                voxel = 0.5 * float(np.median(r))
            files = bake.bake_vdb(anim, bpy.path.abspath(self.directory), frames, times, voxel=voxel,
                                  radius_scale=obj.gaussfluids.radius_scale)
        except Exception as e:
            self.report({"ERROR"}, f"OpenVDB bake to {self.directory} failed: {e}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"wrote {len(files)} OpenVDB files to {self.directory}")
        return {"FINISHED"}


class GAUSSFLUIDS_OT_reload(bpy.types.Operator):
    """Read the active object's reconstruction file again"""

    bl_idname = "gaussfluids.reload"
    bl_label = "Reload Reconstruction"

    @classmethod
    def poll(cls, context):
        return _driven(context) is not None

    def execute(self, context):
        animation._CACHE.clear()
        animation.STATUS.clear()
        animation.on_frame_change(context.scene)
        return {"FINISHED"}


class GAUSSFLUIDS_OT_render_dataset(bpy.types.Operator):
    """Render a multiview training dataset of a simulation (sim.h5) with the toolkit's dataset renderer,
    in a separate Blender process so that this scene is left as it is"""

    bl_idname = "gaussfluids.render_dataset"
    bl_label = "Render Training Dataset"

    sim: bpy.props.StringProperty(name="Simulation", subtype="FILE_PATH", description="sim.h5 from gf-cli simulate")
    out: bpy.props.StringProperty(name="Output Folder", subtype="DIR_PATH")
    views: bpy.props.IntProperty(name="Views", default=5, min=1)
    test_views: bpy.props.IntProperty(name="Held-out Views", default=1, min=0)
    resolution: bpy.props.IntProperty(name="Resolution", default=400, min=8)
    samples: bpy.props.IntProperty(name="Samples", default=32, min=1)
    frames: bpy.props.StringProperty(name="Frames", default=":", description="START:END:STEP over the simulation's frames")
    material: bpy.props.EnumProperty(name="Material", default="auto", items=[
        ("auto", "Auto", "honey for a honey scene, else water"), ("water", "Water", ""),
        ("honey", "Honey", ""), ("smoke", "Smoke", "")])
    seed: bpy.props.IntProperty(name="Seed", default=0)
    force: bpy.props.BoolProperty(name="Start Afresh", default=False,
                                  description="Replace a dataset of another simulation or other options")

    _proc = None
    _timer = None

    def command(self):
        """The render script of render_data/ in a fresh Blender: this Blender's binary with -b, or
        this Python when Blender runs as the bpy module."""
        from .gf_core.formats.hdf5 import read_sim
        from .render_data import render_dataset as rd

        sim_path = bpy.path.abspath(self.sim)
        out = bpy.path.abspath(self.out)
        if not self.sim or not self.out:
            raise ValueError("choose a simulation file and an output folder")
        sim = read_sim(sim_path)  # validates before any rendering
        npz, digest = rd.particles_npz(sim, sim_path, out)
        opts = ["--views", self.views, "--test-views", self.test_views, "--resolution", self.resolution,
                "--samples", self.samples, "--frames", self.frames, "--material", self.material,
                "--seed", self.seed] + (["--force"] if self.force else [])
        binary = bpy.app.binary_path
        is_blender = bool(binary) and "python" not in os.path.basename(binary).lower()
        cmd = rd.render_command(binary if is_blender else sys.executable, npz, out, digest, opts, blender=is_blender)
        return cmd, sim_path, out

    def finish(self, rc, sim_path, out):
        import shutil

        if rc != 0:
            self.report({"ERROR"}, f"dataset rendering into {out} failed (exit {rc}); see the console")
            return {"CANCELLED"}
        gt = os.path.join(out, "gt_sim.h5")  # the npz hand-over names it; copy the original beside
        shutil.copyfile(sim_path, gt + ".partial")
        os.replace(gt + ".partial", gt)
        self.report({"INFO"}, f"dataset written to {out}")
        return {"FINISHED"}

    def execute(self, context):
        try:
            cmd, sim_path, out = self.command()
        except Exception as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        print("GaussFluids:", " ".join(map(str, cmd)))
        if bpy.app.background:  # headless: render now, in the foreground
            rc = subprocess.call(cmd)
            return self.finish(rc, sim_path, out)
        self._proc = subprocess.Popen(cmd)
        self._args = (sim_path, out)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        self.report({"INFO"}, f"rendering a dataset into {out} in the background")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER" or self._proc.poll() is None:
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        return self.finish(self._proc.returncode, *self._args)

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(self)


CLASSES = (GAUSSFLUIDS_OT_import, GAUSSFLUIDS_OT_bake_usd, GAUSSFLUIDS_OT_bake_vdb, GAUSSFLUIDS_OT_reload,
           GAUSSFLUIDS_OT_render_dataset)
