"""The point cloud that follows a reconstruction: creation, per-frame update, handlers.

Time mapping: a scene frame f (sub-frames included) shows reconstruction time
    t = t_min + (f - start_frame) * speed / fps      [seconds]
Outside [t_min, t_max] the particles are clamped to the nearest end of the clip (the decoder does
not extrapolate), the velocity is 0, and the object reports it once per playback (console and the
sidebar). Every update goes through ``foreach_set`` on the point attributes.
"""

import json
import os

import bpy
import numpy as np

from .gf_core.formats.decoder_np import ParticleAnimation
from .gf_core.formats.hdf5 import read_recon

_CACHE = {}       # absolute path -> (stat key, ParticleAnimation)
STATUS = {}       # object name -> text shown in the sidebar (out of range, errors)


def load_animation(path: str) -> ParticleAnimation:
    """The decoder for ``path`` (a recon.h5), read once and kept while the file is unchanged."""
    path = os.path.abspath(bpy.path.abspath(path))
    st = os.stat(path)
    key = (st.st_mtime_ns, st.st_size)
    hit = _CACHE.get(path)
    if hit is None or hit[0] != key:
        hit = (key, ParticleAnimation(read_recon(path), source=path))
        _CACHE[path] = hit
    return hit[1]


def metadata(anim: ParticleAnimation, path: str) -> dict:
    r = anim.recon
    cfg = r.config or {}
    return {"file": os.path.basename(path), "particles": anim.num_particles,
            "time_range_s": [float(r.time_min), float(r.time_max)], "decoder": r.decoder is not None,
            "sh_degree": r.sh_degree, "channels": r.channels, "spacing_m": cfg.get("spacing"),
            "metrics": r.metrics}


def scene_time(settings, frame: float) -> float:
    anim = load_animation(settings.filepath)
    return anim.time.t_min + (frame - settings.start_frame) * settings.speed / settings.fps


def create_point_cloud(name: str, n: int, collection):
    """A point-cloud object with ``n`` points: ``PointCloud.resize`` where Blender has it, else a
    vertex mesh converted to a point cloud (Blender 4.5 - 5.0; the convert target "POINTCLOUD" is not in 4.2 - 4.4)."""
    if hasattr(bpy.types.PointCloud, "resize"):
        pc = bpy.data.pointclouds.new(name)
        pc.resize(n)
        obj = bpy.data.objects.new(name, pc)
        collection.objects.link(obj)
        return obj
    me = bpy.data.meshes.new(name)
    me.vertices.add(n)
    obj = bpy.data.objects.new(name, me)
    collection.objects.link(obj)
    view_layer = bpy.context.view_layer
    for o in view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    view_layer.objects.active = obj
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj],
                                   selected_editable_objects=[obj]):
        bpy.ops.object.convert(target="POINTCLOUD")
    obj = view_layer.objects.active
    if me.users == 0:
        bpy.data.meshes.remove(me)
    if obj.type != "POINTCLOUD" or len(obj.data.points) != n:
        raise RuntimeError(f"could not make a point cloud of {n} points (got {obj.type})")
    return obj


def _attribute(pc, name: str, kind: str):
    a = pc.attributes.get(name)
    if a is None or a.data_type != kind or a.domain != "POINT":
        if a is not None:
            pc.attributes.remove(a)
        a = pc.attributes.new(name, kind, "POINT")
    return a


def import_reconstruction(path: str, context, *, fps=None, start_frame=None, speed=1.0, radius_scale=1.5,
                          preset="water", velocity=True):
    """Make the object for ``path`` and show it at the current frame. Errors name the file."""
    from . import presets

    anim = load_animation(path)
    scene = context.scene
    name = os.path.splitext(os.path.basename(path))[0]
    obj = create_point_cloud(f"gf_{name}", anim.num_particles, context.collection or scene.collection)
    pc = obj.data
    _attribute(pc, "radius", "FLOAT")
    _attribute(pc, "velocity", "FLOAT_VECTOR")
    # the reconstruction's own view-independent colour and opacity, for looks that use them
    _attribute(pc, "gf_color", "FLOAT_COLOR").data.foreach_set(
        "color", np.concatenate([anim.color, anim.opacity[:, None]], 1).astype(np.float32).ravel())
    _attribute(pc, "gf_opacity", "FLOAT").data.foreach_set("value", anim.opacity.astype(np.float32))
    s = obj.gaussfluids
    # settings first, the file last: their update callbacks do nothing until the file is set
    s.fps = float(fps) if fps else scene.render.fps / scene.render.fps_base
    s.start_frame = float(scene.frame_start if start_frame is None else start_frame)
    s.speed = float(speed)
    s.radius_scale = float(radius_scale)
    s.velocity = bool(velocity)
    s.preset = preset
    s.metadata = json.dumps(metadata(anim, path))
    s.filepath = path
    # renders read the geometry from another thread while handlers write it
    scene.render.use_lock_interface = True
    update_object(obj, scene.frame_current + scene.frame_subframe)
    presets.apply_preset(obj)  # the surface looks size their voxels by the radii
    return obj


def update_object(obj, frame: float) -> None:
    s = obj.gaussfluids
    anim = load_animation(s.filepath)
    t = scene_time(s, frame)
    if anim.time.inside(t):
        STATUS.pop(obj.name, None)
    elif obj.name not in STATUS:
        STATUS[obj.name] = (f"frame {frame:g} is t = {t:.4g} s, outside the reconstruction "
                            f"[{anim.time.t_min:.4g}, {anim.time.t_max:.4g}] s: clamped")
        print(f"GaussFluids: {obj.name}: {STATUS[obj.name]}")
    res = anim.at(t, velocity=s.velocity, warn=False)
    pc = obj.data
    if len(pc.points) != anim.num_particles:
        raise RuntimeError(f"{obj.name} has {len(pc.points)} points; {s.filepath} has {anim.num_particles} particles")
    pc.attributes["position"].data.foreach_set("vector", res["positions"].ravel())
    radius = s.radius_scale * np.exp(res["log_scales"].mean(1))
    _attribute(pc, "radius", "FLOAT").data.foreach_set("value", radius.astype(np.float32))
    if s.velocity:
        _attribute(pc, "velocity", "FLOAT_VECTOR").data.foreach_set("vector", res["velocities"].ravel())
    if anim.color_varies or anim.opacity_varies:  # appearance residuals: the reconstructed look at this time
        _attribute(pc, "gf_color", "FLOAT_COLOR").data.foreach_set(
            "color", np.concatenate([res["colors"], res["opacities"][:, None]], 1).astype(np.float32).ravel())
        _attribute(pc, "gf_opacity", "FLOAT").data.foreach_set("value", res["opacities"].astype(np.float32))
    pc.update_tag()


def driven_objects(scene):
    return [o for o in scene.objects if o.type == "POINTCLOUD" and o.gaussfluids.filepath and o.gaussfluids.live]


@bpy.app.handlers.persistent
def on_frame_change(scene, depsgraph=None):
    frame = scene.frame_current + scene.frame_subframe
    for obj in driven_objects(scene):
        try:
            update_object(obj, frame)
        except Exception as e:  # a missing or broken file must not stop playback or a render
            msg = f"{obj.gaussfluids.filepath}: {e}"
            if STATUS.get(obj.name) != msg:
                STATUS[obj.name] = msg
                print(f"GaussFluids: {obj.name}: {msg}")


@bpy.app.handlers.persistent
def on_load(_file=None, _=None):
    _CACHE.clear()
    STATUS.clear()
    for scene in bpy.data.scenes:
        on_frame_change(scene)


def on_setting_changed(self, context):
    obj = self.id_data
    if obj is not None and obj.type == "POINTCLOUD" and self.filepath and self.live and context is not None:
        STATUS.pop(obj.name, None)
        try:
            update_object(obj, context.scene.frame_current + context.scene.frame_subframe)
        except Exception as e:
            STATUS[obj.name] = f"{self.filepath}: {e}"


def register_handlers():
    unregister_handlers()
    bpy.app.handlers.frame_change_pre.append(on_frame_change)
    bpy.app.handlers.load_post.append(on_load)


def unregister_handlers():
    for hs, fn in ((bpy.app.handlers.frame_change_pre, "on_frame_change"), (bpy.app.handlers.load_post, "on_load")):
        for h in list(hs):
            if getattr(h, "__name__", "") == fn and getattr(h, "__module__", "") == __name__:
                hs.remove(h)
