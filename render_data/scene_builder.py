"""Scene building for dataset rendering, importable by the render script and the Blender extension.

Only bpy, mathutils and numpy. Blender 4.2 - 5.0. Units: metres, z up, gravity -z.
The fluid is one mesh object whose vertices are the particles; a geometry-nodes modifier turns
them into a surface (Points to Volume -> Volume to Mesh, smooth shaded) for liquids or keeps the
volume for smoke. ``set_particles`` moves the vertices for a frame.
"""

from __future__ import annotations

import math

import numpy as np

import bpy
from mathutils import Matrix, Vector

MATERIALS = ("water", "honey", "smoke")


# ---- materials ------------------------------------------------------------------------------------
def _new_material(name: str):
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    if hasattr(mat, "use_nodes") and not mat.use_nodes:
        mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    return mat, nt, out


def make_material(kind: str, transmission: float | None = None):
    """water: glass, IOR 1.33 (as the paper's data), or with ``transmission`` a principled surface
    of that transmission weight (partly opaque, light blue); honey: amber, transmissive, rough;
    smoke: a principled volume."""
    if kind not in MATERIALS:
        raise ValueError(f"unknown material {kind!r}; choose from {', '.join(MATERIALS)}")
    mat, nt, out = _new_material(f"gf_{kind}")
    if kind == "water" and transmission is not None:
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (0.55, 0.75, 0.95, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.05
        bsdf.inputs["IOR"].default_value = 1.33
        bsdf.inputs["Transmission Weight"].default_value = float(transmission)
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    elif kind == "water":
        bsdf = nt.nodes.new("ShaderNodeBsdfGlass")
        bsdf.inputs["Color"].default_value = (0.85, 0.93, 1.0, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.0
        bsdf.inputs["IOR"].default_value = 1.33
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    elif kind == "honey":
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (0.80, 0.36, 0.03, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.25
        bsdf.inputs["IOR"].default_value = 1.49
        bsdf.inputs["Transmission Weight"].default_value = 0.85
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
        absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
        absorb.inputs["Color"].default_value = (0.9, 0.45, 0.05, 1.0)
        absorb.inputs["Density"].default_value = 8.0
        nt.links.new(absorb.outputs[0], out.inputs["Volume"])
    else:
        vol = nt.nodes.new("ShaderNodeVolumePrincipled")
        vol.inputs["Color"].default_value = (0.9, 0.9, 0.92, 1.0)
        vol.inputs["Density"].default_value = 30.0
        nt.links.new(vol.outputs[0], out.inputs["Volume"])
    return mat


def _diffuse(name, color, checker=None):
    mat, nt, out = _new_material(name)
    bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (*color, 1.0)
    if checker:
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Scale"].default_value = checker
        tex.inputs["Color1"].default_value = (*color, 1.0)
        tex.inputs["Color2"].default_value = tuple(0.6 * c for c in color) + (1.0,)
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Color"])
    nt.links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat


# ---- scene ----------------------------------------------------------------------------------------
def reset_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable("cycles", default_set=True, persistent=True)


def configure_render(*, resolution: int, samples: int, seed: int, denoise: bool, threads: int = 0):
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    if sc.render.engine != "CYCLES":
        raise RuntimeError("Cycles is not available in this Blender")
    sc.cycles.device = "CPU"
    sc.cycles.samples = int(samples)
    sc.cycles.seed = int(seed)
    sc.cycles.use_animated_seed = False
    if hasattr(sc.cycles, "use_adaptive_sampling"):
        sc.cycles.use_adaptive_sampling = False  # fixed work per pixel: deterministic, comparable
    if denoise:
        denoisers = [e.identifier for e in type(sc.cycles).bl_rna.properties["denoiser"].enum_items]
        if not denoisers:
            raise RuntimeError("denoising was requested but this Blender build has no denoiser "
                               "(OpenImageDenoise); render without --denoise or use a full Blender")
    sc.cycles.use_denoising = bool(denoise)
    sc.render.resolution_x = sc.render.resolution_y = int(resolution)
    sc.render.resolution_percentage = 100
    sc.render.film_transparent = True
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGBA"
    sc.render.image_settings.color_depth = "8"
    if threads:
        sc.render.threads_mode = "FIXED"
        sc.render.threads = int(threads)
    sc.view_settings.view_transform = "Standard"  # no filmic tone curve: what is rendered is stored
    sc.render.use_persistent_data = True
    for prop in dir(sc.render):  # no date/time/host metadata in the PNGs: same seed, same bytes
        if prop.startswith("use_stamp"):
            setattr(sc.render, prop, False)


def build_world(strength: float = 1.0):
    world = bpy.data.worlds.new("gf_world")
    bpy.context.scene.world = world
    if hasattr(world, "use_nodes") and not world.use_nodes:
        world.use_nodes = True
    nt = world.node_tree
    bg = nt.nodes.get("Background") or nt.nodes.new("ShaderNodeBackground")
    # a vertical gradient (bright sky above, darker ground): structure for refraction, no assets
    coord = nt.nodes.new("ShaderNodeTexCoord")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].position = 0.4
    ramp.color_ramp.elements[0].color = (0.25, 0.25, 0.27, 1.0)
    ramp.color_ramp.elements[1].position = 0.6
    ramp.color_ramp.elements[1].color = (0.85, 0.9, 1.0, 1.0)
    maprange = nt.nodes.new("ShaderNodeMapRange")
    maprange.inputs["From Min"].default_value = -1.0
    nt.links.new(coord.outputs["Generated"], sep.inputs[0])  # world: the view direction
    nt.links.new(sep.outputs["Z"], maprange.inputs["Value"])
    nt.links.new(maprange.outputs["Result"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.get("World Output") or nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    sun = bpy.data.objects.new("gf_sun", bpy.data.lights.new("gf_sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))
    bpy.context.scene.collection.objects.link(sun)
    return world


def _box_mesh(name, lo, hi, open_sides=("top", "front")):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
         (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    faces = {"bottom": (0, 3, 2, 1), "top": (4, 5, 6, 7), "front": (0, 1, 5, 4),
             "back": (2, 3, 7, 6), "left": (3, 0, 4, 7), "right": (1, 2, 6, 5)}
    me = bpy.data.meshes.new(name)
    me.from_pydata(v, [], [f for k, f in faces.items() if k not in open_sides])
    me.update()
    return me


def build_container(domain_min, domain_max, *, show: bool):
    """Floor (checker) and a tank without front and top walls around the domain. Unless ``show``,
    both are invisible to camera rays (they still appear in reflections, refractions and shadows)
    so that the alpha channel is a clean fluid mask."""
    lo, hi = np.asarray(domain_min, float), np.asarray(domain_max, float)
    size = float((hi - lo).max())
    objs = []
    floor_me = bpy.data.meshes.new("gf_floor")
    c = (lo + hi) / 2
    s = 3 * size
    floor_me.from_pydata([(c[0] - s, c[1] - s, lo[2] - 1e-3), (c[0] + s, c[1] - s, lo[2] - 1e-3),
                          (c[0] + s, c[1] + s, lo[2] - 1e-3), (c[0] - s, c[1] + s, lo[2] - 1e-3)],
                         [], [(0, 1, 2, 3)])
    floor = bpy.data.objects.new("gf_floor", floor_me)
    floor.data.materials.append(_diffuse("gf_floor_mat", (0.75, 0.75, 0.72), checker=12.0))
    tank = bpy.data.objects.new("gf_container", _box_mesh("gf_container", lo - 1e-3, hi + 1e-3,
                                                          open_sides=("top", "front", "bottom")))
    tank.data.materials.append(_diffuse("gf_container_mat", (0.55, 0.6, 0.65)))
    for o in (floor, tank):
        bpy.context.scene.collection.objects.link(o)
        if not show and hasattr(o, "visible_camera"):
            o.visible_camera = False
        objs.append(o)
    return objs


# ---- the fluid ------------------------------------------------------------------------------------
def _set_resolution_size(node, voxel_size):
    sock = node.inputs.get("Resolution Mode")
    if sock is not None:  # Blender >= 4.4: a menu socket
        sock.default_value = "Size"
    elif hasattr(node, "resolution_mode"):  # Blender 4.2/4.3: a node property
        node.resolution_mode = "VOXEL_SIZE"
    node.inputs["Voxel Size"].default_value = voxel_size


def fluid_node_group(name: str, material, radius: float, *, volume: bool, from_mesh: bool = True,
                     voxel_scale: float = 0.5, blob: float = 2.5, smooth_iterations: int = 6):
    """Geometry nodes that turn particles into what is rendered: a volume of spheres of radius
    ``blob * radius`` (smoke), or that volume's smoothed surface (liquids), with ``material``.
    ``from_mesh``: the input is a mesh whose vertices are the particles (the dataset renderer);
    otherwise a point cloud (the Blender extension)."""
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nin, nout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    points = nin.outputs[0]
    if from_mesh:
        to_points = ng.nodes.new("GeometryNodeMeshToPoints")
        to_points.inputs["Radius"].default_value = blob * radius
        ng.links.new(nin.outputs[0], to_points.inputs["Mesh"])
        points = to_points.outputs["Points"]
    to_vol = ng.nodes.new("GeometryNodePointsToVolume")
    to_vol.inputs["Density"].default_value = 1.0
    to_vol.inputs["Radius"].default_value = blob * radius
    _set_resolution_size(to_vol, voxel_scale * radius)
    set_mat = ng.nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = material
    ng.links.new(points, to_vol.inputs["Points"])
    if volume:
        ng.links.new(to_vol.outputs["Volume"], set_mat.inputs["Geometry"])
    else:
        to_mesh = ng.nodes.new("GeometryNodeVolumeToMesh")
        _set_resolution_size(to_mesh, voxel_scale * radius)
        to_mesh.inputs["Threshold"].default_value = 0.5
        # relax the union-of-spheres bumps: blur vertex positions over the mesh
        pos = ng.nodes.new("GeometryNodeInputPosition")
        blur = ng.nodes.new("GeometryNodeBlurAttribute")
        blur.data_type = "FLOAT_VECTOR"
        blur.inputs["Iterations"].default_value = smooth_iterations
        set_pos = ng.nodes.new("GeometryNodeSetPosition")
        smooth = ng.nodes.new("GeometryNodeSetShadeSmooth")
        ng.links.new(to_vol.outputs["Volume"], to_mesh.inputs["Volume"])
        ng.links.new(pos.outputs["Position"], blur.inputs[0])
        ng.links.new(to_mesh.outputs["Mesh"], set_pos.inputs["Geometry"])
        ng.links.new(blur.outputs[0], set_pos.inputs["Position"])
        ng.links.new(set_pos.outputs["Geometry"], smooth.inputs[0])
        ng.links.new(smooth.outputs[0], set_mat.inputs["Geometry"])
    ng.links.new(set_mat.outputs["Geometry"], nout.inputs[0])
    return ng


def build_fluid(n_particles: int, radius: float, material: str, *, voxel_scale: float = 0.5,
                blob: float = 2.5, smooth_iterations: int = 6, transmission: float | None = None):
    """A mesh of ``n_particles`` vertices with a surface-building geometry-nodes modifier."""
    me = bpy.data.meshes.new("gf_particles")
    me.vertices.add(int(n_particles))
    obj = bpy.data.objects.new("gf_fluid", me)
    bpy.context.scene.collection.objects.link(obj)
    ng = fluid_node_group("gf_surface", make_material(material, transmission), radius, volume=material == "smoke",
                          voxel_scale=voxel_scale, blob=blob, smooth_iterations=smooth_iterations)
    mod = obj.modifiers.new("gf_surface", "NODES")
    mod.node_group = ng
    return obj


def set_particles(obj, positions: np.ndarray) -> None:
    """Move the fluid's vertices to ``positions`` (N, 3) -- foreach_set, no Python loop."""
    p = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1)
    me = obj.data
    if len(me.vertices) * 3 != p.size:
        raise ValueError(f"frame has {p.size // 3} particles, the fluid mesh has {len(me.vertices)}")
    me.vertices.foreach_set("co", p)
    me.update()


# ---- cameras --------------------------------------------------------------------------------------
def look_at_matrix(eye, target, up=(0.0, 0.0, 1.0)) -> Matrix:
    """Camera-to-world (Blender/OpenGL: the camera looks down its -Z, +Y up)."""
    eye, target, up = Vector(eye), Vector(target), Vector(up)
    fwd = (target - eye).normalized()
    right = fwd.cross(up).normalized()
    cam_up = right.cross(fwd)
    m = Matrix.Identity(4)
    for r in range(3):
        m[r][0], m[r][1], m[r][2], m[r][3] = right[r], cam_up[r], -fwd[r], eye[r]
    return m


def camera_rig(domain_min, domain_max, *, views: int, test_views: int = 0, fov_deg: float = 40.0,
               arc_deg: float = 90.0, elevation_deg: float = 15.0, margin: float = 1.15,
               test_elevation_deg: float | None = None):
    """Camera-to-world matrices on a frontal arc (the -y side, as NeuroFluid's five frontal cameras),
    far enough for the whole domain to fit the field of view. Test cameras sit between the
    training ones (at ``test_elevation_deg``, default the training cameras' elevation). Returns
    (train, test) lists of (name, Matrix)."""
    lo, hi = np.asarray(domain_min, float), np.asarray(domain_max, float)
    target = (lo + hi) / 2
    radius = margin * 0.5 * float(np.linalg.norm(hi - lo)) / math.tan(math.radians(fov_deg) / 2)

    def at(angle, elevation=elevation_deg):
        el = math.radians(elevation)
        a = math.radians(angle)
        eye = target + radius * np.array([math.sin(a) * math.cos(el), -math.cos(a) * math.cos(el), math.sin(el)])
        return look_at_matrix(eye, target)

    train = [(f"view_{k}", at(a)) for k, a in enumerate(np.linspace(-arc_deg / 2, arc_deg / 2, views))] \
        if views > 1 else [("view_0", at(0.0))]
    step = arc_deg / max(views - 1, 1)
    tel = elevation_deg if test_elevation_deg is None else test_elevation_deg
    test = [(f"test_{k}", at(-arc_deg / 2 + step * (k + 0.5), tel)) for k in range(test_views)]
    return train, test


def make_camera(name: str, c2w: Matrix, fov_deg: float):
    cam_data = bpy.data.cameras.new(name)
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle_x = math.radians(fov_deg)
    cam_data.clip_start = 0.01
    cam_data.clip_end = 1000.0
    obj = bpy.data.objects.new(name, cam_data)
    obj.matrix_world = c2w
    bpy.context.scene.collection.objects.link(obj)
    return obj


def build_scene(*, n_particles: int, radius: float, material: str, domain_min, domain_max,
                views: int, test_views: int, resolution: int, samples: int, seed: int,
                denoise: bool, fov_deg: float = 40.0, show_container: bool = False, threads: int = 0,
                arc_deg: float = 90.0, elevation_deg: float = 15.0, test_elevation_deg: float | None = None,
                blob: float = 2.5, transmission: float | None = None):
    """Everything but the particle positions. Returns (fluid object, train cameras, test cameras)."""
    reset_scene()
    configure_render(resolution=resolution, samples=samples, seed=seed, denoise=denoise, threads=threads)
    build_world()
    build_container(domain_min, domain_max, show=show_container)
    fluid = build_fluid(n_particles, radius, material, blob=blob, transmission=transmission)
    train, test = camera_rig(domain_min, domain_max, views=views, test_views=test_views, fov_deg=fov_deg,
                             arc_deg=arc_deg, elevation_deg=elevation_deg, test_elevation_deg=test_elevation_deg)
    cams = [make_camera(n, m, fov_deg) for n, m in train]
    tcams = [make_camera(n, m, fov_deg) for n, m in test]
    return fluid, cams, tcams


def render_to(path: str, camera) -> None:
    sc = bpy.context.scene
    sc.camera = camera
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
