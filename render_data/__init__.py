"""Headless Blender scripts that render synthetic multiview datasets (bpy + numpy, no torch).

``scene_builder`` builds the scene (fluid surface from particles, materials, container, world,
camera rig); ``render_dataset`` is the ``blender -b -P`` / ``python`` entry point.
"""
