"""GaussFluids for Blender: a reconstruction (``recon.h5``) as an animated point cloud.

File > Import > GaussFluids reconstruction (.h5) makes a point-cloud object whose positions, radii
and ``velocity`` attribute follow the time-continuous decoder (paper Eq. 4, evaluated in numpy:
``gf_core/formats/decoder_np.py``) at the scene's current frame, sub-frames included, through a persistent
``frame_change_pre`` handler. The sidebar (View3D > N > GaussFluids) switches material presets
(style transfer, paper Sec. 4.3.3), tunes radius, colour and time mapping, bakes USD / OpenVDB
caches, and renders a multiview training dataset of a ``sim.h5`` with ``render_data/``.
No torch: the toolkit's torch-free modules travel inside the extension zip.
"""

import bpy

from . import animation, operators, presets, ui


class GaussFluidsSettings(bpy.types.PropertyGroup):
    """Per-object settings; ``filepath`` set means the object is driven by a reconstruction."""

    filepath: bpy.props.StringProperty(name="Reconstruction", subtype="FILE_PATH",
                                       description="recon.h5 that drives this object")
    live: bpy.props.BoolProperty(name="Live", default=True, update=animation.on_setting_changed,
                                 description="Follow the decoder on every frame change (off after a bake replaces it)")
    fps: bpy.props.FloatProperty(name="FPS", default=24.0, min=1e-3, update=animation.on_setting_changed,
                                 description="Blender frames per second of reconstruction time")
    start_frame: bpy.props.FloatProperty(name="Start Frame", default=1.0, update=animation.on_setting_changed,
                                         description="The frame that shows the reconstruction's first time")
    speed: bpy.props.FloatProperty(name="Speed", default=1.0, update=animation.on_setting_changed,
                                   description="Reconstruction seconds per scene second (0.5: slow motion)")
    radius_scale: bpy.props.FloatProperty(name="Radius Scale", default=1.5, min=1e-4,
                                          update=animation.on_setting_changed,
                                          description="Point radius = this x the particle's Gaussian size (geometric mean); the point looks")
    surface_radius: bpy.props.FloatProperty(name="Surface Radius", default=1.25, min=0.1, max=10.0,
                                            update=presets.on_preset_changed,
                                            description="Surface and smoke looks: sphere radius around each particle, "
                                                        "in particle spacings (the dataset renderer uses 1.25)")
    velocity: bpy.props.BoolProperty(name="Velocity", default=True, update=animation.on_setting_changed,
                                     description="Write the 'velocity' attribute (m/s) for motion blur")
    preset: bpy.props.EnumProperty(name="Look", items=presets.ENUM_ITEMS, default="water",
                                   update=presets.on_preset_changed)
    color: bpy.props.FloatVectorProperty(name="Colour", subtype="COLOR", size=4, min=0.0, max=1.0,
                                         default=(1.0, 1.0, 1.0, 1.0), update=presets.on_color_changed,
                                         description="Tint of the look (multiplies the preset's colour)")
    metadata: bpy.props.StringProperty(name="Metadata", description="JSON: what the reconstruction says of itself")


CLASSES = (GaussFluidsSettings,) + operators.CLASSES + ui.CLASSES


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.gaussfluids = bpy.props.PointerProperty(type=GaussFluidsSettings)
    bpy.types.TOPBAR_MT_file_import.append(ui.menu_import)
    animation.register_handlers()


def unregister():
    animation.unregister_handlers()
    bpy.types.TOPBAR_MT_file_import.remove(ui.menu_import)
    del bpy.types.Object.gaussfluids
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
