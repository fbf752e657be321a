"""The sidebar panel (View3D > Sidebar > GaussFluids) and the File > Import entry."""

import json

import bpy

from . import animation


def menu_import(self, context):
    self.layout.operator("import_scene.gaussfluids", text="GaussFluids reconstruction (.h5)")


class GAUSSFLUIDS_PT_panel(bpy.types.Panel):
    bl_label = "GaussFluids"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GaussFluids"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        layout.operator("import_scene.gaussfluids", icon="IMPORT")
        layout.operator("gaussfluids.render_dataset", icon="RENDER_ANIMATION")
        if obj is None or obj.type != "POINTCLOUD" or not obj.gaussfluids.filepath:
            layout.label(text="Select an imported reconstruction")
            return
        s = obj.gaussfluids
        box = layout.box()
        box.label(text="Look")
        box.prop(s, "preset", text="")
        box.prop(s, "color")
        box.prop(s, "radius_scale")
        box.prop(s, "surface_radius")
        box = layout.box()
        box.label(text="Time")
        box.prop(s, "live")
        box.prop(s, "fps")
        box.prop(s, "start_frame")
        box.prop(s, "speed")
        box.prop(s, "velocity")
        status = animation.STATUS.get(obj.name)
        if status:
            box.label(text=status, icon="ERROR")
        box = layout.box()
        box.label(text="Bake")
        box.operator("gaussfluids.bake_usd", icon="EXPORT")
        box.operator("gaussfluids.bake_vdb", icon="VOLUME_DATA")
        box.operator("gaussfluids.reload", icon="FILE_REFRESH")
        box = layout.box()
        box.label(text="Reconstruction")
        try:
            meta = json.loads(s.metadata or "{}")
        except ValueError:
            meta = {}
        for key in ("file", "particles", "time_range_s", "decoder", "sh_degree", "channels", "spacing_m"):
            if key in meta:
                box.label(text=f"{key}: {meta[key]}")
        for key, val in (meta.get("metrics") or {}).items():
            box.label(text=f"{key}: {val:.4g}" if isinstance(val, float) else f"{key}: {val}")


CLASSES = (GAUSSFLUIDS_PT_panel,)
