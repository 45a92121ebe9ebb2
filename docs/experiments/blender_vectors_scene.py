"""A Cycles sequence with the Vector and Denoising Data passes: a checkered floor, a box and a sphere, the
camera trucking and panning over 4 frames (or --frames N), 96x64, multilayer EXRs with the light passes
(docs/experiments/blender_vectors.py). Cycles' default pixel filter (Blackman-Harris, 1.5 px), or --box.

    /tmp/bpy/bin/python docs/experiments/blender_vectors_scene.py -- [--box] [--frames N] [--seed S] SPP OUT_PATTERN

--seed: Cycles' seed (0 by default); a reference rendered with another seed shares no sample with the inputs.
"""
import math
import sys

import bpy

out, samples = sys.argv[-1], int(sys.argv[-2])
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = samples
scene.cycles.use_animated_seed = True          # independent noise in every frame, as a render farm's
scene.cycles.seed = int(sys.argv[sys.argv.index("--seed") + 1]) if "--seed" in sys.argv else 0
scene.cycles.use_denoising = False
scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 96, 64, 100
scene.render.use_motion_blur = False           # Cycles writes the Vector pass only without motion blur
scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
scene.render.image_settings.color_depth = "32"
layer = scene.view_layers[0]
layer.use_pass_vector = True
layer.use_pass_z = True
layer.use_pass_normal = True
layer.cycles.denoising_store_passes = True     # Denoising Albedo and Normal
# the light passes, from which denoise reads the light components (exr.cycles_components)
for name in ("diffuse_direct", "diffuse_indirect", "diffuse_color", "glossy_direct", "glossy_indirect", "glossy_color",
             "transmission_direct", "transmission_indirect", "transmission_color", "emit", "environment"):
    setattr(layer, f"use_pass_{name}", True)
if "--box" in sys.argv:                        # a box pixel filter 1 pixel wide: independent pixels
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0


def material(name: str, checker: bool):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes = mat.node_tree
    bsdf = nodes.nodes["Principled BSDF"]
    if checker:
        tex = nodes.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Scale"].default_value = 12.0
        tex.inputs["Color1"].default_value = (0.9, 0.2, 0.1, 1)
        tex.inputs["Color2"].default_value = (0.1, 0.3, 0.9, 1)
        nodes.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    else:
        bsdf.inputs["Base Color"].default_value = (0.2, 0.8, 0.3, 1)
    return mat


bpy.ops.mesh.primitive_plane_add(size=20)
bpy.context.object.data.materials.append(material("floor", True))
bpy.ops.mesh.primitive_cube_add(size=1.5, location=(0.5, 0, 0.75))
bpy.context.object.data.materials.append(material("box", True))
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, location=(-1.5, 1.0, 0.7))
bpy.context.object.data.materials.append(material("ball", False))
bpy.ops.object.light_add(type="SUN", location=(0, 0, 10))
bpy.context.object.data.energy = 3.0
bpy.context.object.rotation_euler = (0.6, 0.3, 0.0)
world = bpy.data.worlds.new("sky")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.5
scene.world = world
bpy.ops.object.camera_add()
camera = bpy.context.object
scene.camera = camera
camera.data.lens = 30
frames = int(sys.argv[sys.argv.index("--frames") + 1]) if "--frames" in sys.argv else 4
for f in range(frames):      # a truck to the left and a pan, 1.5 degrees per frame
    camera.location = (6.0 - 0.35 * f, -6.0 + 0.1 * f, 4.0 + 0.05 * f)
    camera.rotation_euler = (math.radians(63), 0, math.radians(45 + 1.5 * f))
    camera.keyframe_insert("location", frame=f + 1)
    camera.keyframe_insert("rotation_euler", frame=f + 1)
scene.frame_start, scene.frame_end = 1, frames
scene.render.filepath = out
bpy.ops.render.render(animation=True)
