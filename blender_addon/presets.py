"""Material presets: the style transfer of paper Sec. 4.3.3 (Fig. 8; the pink re-render of Fig. 6).

A look is a material and, for liquids and smoke, a geometry-nodes modifier that turns the points
into what is rendered: the smoothed surface of a union of spheres (water, honey, pink), a volume
(smoke), or the points themselves as spheres (glow, reconstructed colour). The physical looks and
the surface/volume node group are the ones the dataset renderer uses (``render_data/scene_builder``),
so a restyled reconstruction and the training data are built the same way. Each object gets its
own copy of its material, so tinting one fluid leaves the others alone.
"""

import bpy
import numpy as np

from .render_data import scene_builder

# (id, label, description, kind): kind "surface" | "volume" | "points"
PRESETS = (
    ("water", "Water", "Clear glass, IOR 1.33, on the particles' smoothed surface", "surface"),
    ("honey", "Honey", "Amber, transmissive, absorbing, on the smoothed surface", "surface"),
    ("smoke", "Smoke", "A volume built from the points (principled volume)", "volume"),
    ("pink", "Pink", "The paper's pink re-render: a glossy pink surface", "surface"),
    ("glow", "Glow", "Emissive spheres in the reconstruction's own colours", "points"),
    ("recon", "Reconstructed colour", "Diffuse spheres in the reconstruction's own colours", "points"),
)
ENUM_ITEMS = [(p[0], p[1], p[2]) for p in PRESETS]
KIND = {p[0]: p[3] for p in PRESETS}
MODIFIER = "gf_look"


def _fresh(name):
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    if hasattr(mat, "use_nodes") and not mat.use_nodes:
        mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    return mat, nt, nt.nodes.new("ShaderNodeOutputMaterial")


def _rgba(sockets, name):
    """The colour socket called ``name`` (a Mix node has a float, a vector and a colour 'A')."""
    return next(s for s in sockets if s.name == name and s.type == "RGBA")


def _tint_mix(nt, color_socket_out):
    """A multiply node named gf_tint between ``color_socket_out`` and what it feeds; B is the tint."""
    mix = nt.nodes.new("ShaderNodeMix")
    mix.name = "gf_tint"
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    nt.links.new(color_socket_out, _rgba(mix.inputs, "A"))
    _rgba(mix.inputs, "B").default_value = (1.0, 1.0, 1.0, 1.0)
    return _rgba(mix.outputs, "Result")


def _attribute_colour(nt):
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = "gf_color"  # "color" itself does not reach Cycles (Blender 5.0)
    return attr.outputs["Color"]


def make_look_material(preset: str, name: str):
    """The preset's material under ``name`` (created or rebuilt)."""
    if preset in ("water", "honey", "smoke"):
        base = scene_builder.make_material(preset)
        mat = bpy.data.materials.get(name)
        if mat is not None:
            bpy.data.materials.remove(mat)
        mat = base.copy()
        mat.name = name
        return mat
    mat, nt, out = _fresh(name)
    if preset == "pink":
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (1.0, 0.36, 0.62, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.12
        bsdf.inputs["Coat Weight"].default_value = 0.6
        bsdf.inputs["Subsurface Weight"].default_value = 0.2
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    elif preset == "glow":
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Strength"].default_value = 4.0
        nt.links.new(_tint_mix(nt, _attribute_colour(nt)), em.inputs["Color"])
        nt.links.new(em.outputs[0], out.inputs["Surface"])
    elif preset == "recon":
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Roughness"].default_value = 0.5
        nt.links.new(_tint_mix(nt, _attribute_colour(nt)), bsdf.inputs["Base Color"])
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    else:
        raise ValueError(f"unknown look {preset!r}; choose from {', '.join(KIND)}")
    return mat


def _tint_socket(mat):
    """The colour input that the tint drives, and its colour before any tint."""
    nt = mat.node_tree
    node = nt.nodes.get("gf_tint")
    if node is not None:
        return _rgba(node.inputs, "B"), (1.0, 1.0, 1.0, 1.0)
    for n in nt.nodes:
        for key in ("Base Color", "Color"):
            sock = n.inputs.get(key) if hasattr(n, "inputs") else None
            if sock is not None and not sock.is_linked and sock.type == "RGBA":
                if "gf_base" not in mat:
                    mat["gf_base"] = list(sock.default_value)
                return sock, tuple(mat["gf_base"])
    return None, None


def apply_tint(mat, color) -> None:
    sock, base = _tint_socket(mat)
    if sock is not None:
        sock.default_value = tuple(float(b) * float(c) for b, c in zip(base, color))


def apply_preset(obj) -> None:
    """Give ``obj`` (a driven point cloud) its look: material, tint and, for surfaces and smoke,
    the geometry-nodes modifier."""
    s = obj.gaussfluids
    preset = s.preset
    mat = make_look_material(preset, f"{obj.name}_{preset}")
    apply_tint(mat, s.color)
    pc = obj.data
    pc.materials.clear()
    pc.materials.append(mat)
    mod = obj.modifiers.get(MODIFIER)
    if mod is not None:
        old = mod.node_group
        obj.modifiers.remove(mod)
        if old is not None and old.users == 0:
            bpy.data.node_groups.remove(old)
    kind = KIND[preset]
    if kind == "points":
        return
    # surfaces and volumes: spheres of surface_radius particle spacings, voxels of a quarter
    # spacing -- the dataset renderer's sizes for simulated particles (radius = spacing / 2)
    spacing = particle_spacing(obj)
    ng = scene_builder.fluid_node_group(f"{obj.name}_look", mat, 0.5 * spacing, volume=kind == "volume",
                                        from_mesh=False, blob=2.0 * s.surface_radius, voxel_scale=0.5)
    mod = obj.modifiers.new(MODIFIER, "NODES")
    mod.node_group = ng


def particle_spacing(obj) -> float:
    """The reconstruction's particle spacing (recorded by gf-cli reconstruct), else estimated
    from the points' bounding box and count."""
    import json

    try:
        spacing = json.loads(obj.gaussfluids.metadata or "{}").get("spacing_m")
    except ValueError:
        spacing = None
    if spacing:
        return float(spacing)
    pc = obj.data
    p = np.empty(len(pc.points) * 3, np.float32)
    pc.attributes["position"].data.foreach_get("vector", p)
    p = p.reshape(-1, 3)
    ext = np.maximum(p.max(0) - p.min(0), 1e-6) if len(p) else np.ones(3)
    return float((np.prod(ext) / max(len(p), 1)) ** (1 / 3))


def on_preset_changed(self, context):
    obj = self.id_data
    if obj is not None and obj.type == "POINTCLOUD" and self.filepath:
        apply_preset(obj)


def on_color_changed(self, context):
    obj = self.id_data
    if obj is None or obj.type != "POINTCLOUD" or not self.filepath:
        return
    for mat in obj.data.materials:
        if mat is not None:
            apply_tint(mat, self.color)
