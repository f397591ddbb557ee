"""Renders a rig capture with Blender's Cycles path tracer, as a validation
renderer independent of the sim rig's own.

Run headless by `aggscan validate --renderer blender` (cli/blender_render.cpp):

    blender -b --factory-startup -noaudio --python-exit-code 3 \
        --python render_capture.py -- SCENE_DIR

SCENE_DIR/scene.json (format aggscan-blender-scene-1, written by the C++
side from the sim world and its truth) holds the camera, the disc with its
colour labels, the rock mesh in its own frame with the object markers, the
look (disc and floor, lighting, stone) and every view's true pose. For each
view this writes SCENE_DIR/<image> (8-bit sRGB PNG) and SCENE_DIR/<mask>
(the rock's true silhouette from Cycles' object index pass, 0/255 PNG), and
at the end SCENE_DIR/render_report.json with the seconds each frame took.

Units: scene.json is in millimetres; the Blender scene is in metres (lights
and the path tracer's ray offsets are tuned for metric scenes), except the
rock's mesh, which keeps millimetres in its object space under a 0.001 scale
so that the stone and pencil shaders work in millimetres.

Cameras: scene.json's are OpenCV's (x right, y down, z forward, pixel centres
at integer coordinates); Blender's look down their -z with y up.
"""

import json
import math
import os
import random
import sys
import time

import bpy
import numpy as np
from mathutils import Matrix, Vector

sys.dont_write_bytecode = True  # no __pycache__ next to an installed script
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import denoise  # noqa: E402  (beside this script, found through sys.path)

MM = 0.001  # metres per millimetre


def fail(msg):
    sys.stderr.write("render_capture.py: " + msg + "\n")
    sys.exit(3)


def matrix4(flat):
    if len(flat) != 16:
        fail("a 4x4 matrix needs 16 numbers, got %d" % len(flat))
    return Matrix([flat[0:4], flat[4:8], flat[8:12], flat[12:16]])


def mm_to_m(m):
    """A rigid transform in mm as one in metres."""
    out = m.copy()
    for r in range(3):
        out[r][3] = m[r][3] * MM
    return out


# --- node helpers -------------------------------------------------------------


class Nodes:
    """Builds a material's node graph with short calls."""

    def __init__(self, mat):
        mat.use_nodes = True
        self.tree = mat.node_tree
        self.tree.nodes.clear()
        self.links = self.tree.links

    def node(self, kind, **props):
        n = self.tree.nodes.new(kind)
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def link(self, a, b):
        self.links.new(a, b)

    def math(self, op, a, b=None, clamp=False):
        n = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        self._in(n.inputs[0], a)
        if b is not None:
            self._in(n.inputs[1], b)
        return n.outputs[0]

    def vmath(self, op, a, b=None):
        n = self.node("ShaderNodeVectorMath", operation=op)
        self._in(n.inputs[0], a)
        if b is not None:
            self._in(n.inputs[1], b)
        return n.outputs["Value"] if op in ("DOT_PRODUCT", "LENGTH", "DISTANCE") else n.outputs["Vector"]

    def mix(self, fac, a, b):
        n = self.node("ShaderNodeMixRGB", blend_type="MIX")
        self._in(n.inputs["Fac"], fac)
        self._in(n.inputs["Color1"], a)
        self._in(n.inputs["Color2"], b)
        return n.outputs["Color"]

    def ramp(self, fac, stops):
        n = self.node("ShaderNodeValToRGB")
        self._in(n.inputs["Fac"], fac)
        els = n.color_ramp.elements
        while len(els) > 1:
            els.remove(els[-1])
        els[0].position, els[0].color = stops[0][0], tuple(stops[0][1]) + (1.0,)
        for pos, col in stops[1:]:
            e = els.new(pos)
            e.color = tuple(col) + (1.0,)
        return n.outputs["Color"]

    def noise(self, vec, scale, detail=2.0, roughness=0.5):
        n = self.node("ShaderNodeTexNoise")
        n.inputs["Scale"].default_value = scale
        n.inputs["Detail"].default_value = detail
        n.inputs["Roughness"].default_value = roughness
        self._in(n.inputs["Vector"], vec)
        return n.outputs["Fac"]

    def voronoi(self, vec, scale, feature="F1", out="Distance"):
        n = self.node("ShaderNodeTexVoronoi", feature=feature)
        n.inputs["Scale"].default_value = scale
        self._in(n.inputs["Vector"], vec)
        return n.outputs[out]

    def value(self, v):
        n = self.node("ShaderNodeValue")
        n.outputs[0].default_value = v
        return n.outputs[0]

    def vector(self, v):
        n = self.node("ShaderNodeCombineXYZ")
        for i in range(3):
            n.inputs[i].default_value = v[i]
        return n.outputs[0]

    def rgb(self, c):
        n = self.node("ShaderNodeRGB")
        n.outputs[0].default_value = tuple(c) + (1.0,)
        return n.outputs[0]

    def bsdf(self, color, roughness, specular=0.5, clearcoat=0.0, normal=None):
        b = self.node("ShaderNodeBsdfPrincipled")
        self._in(b.inputs["Base Color"], color)
        self._in(b.inputs["Roughness"], roughness)
        b.inputs["Specular"].default_value = specular
        b.inputs["Clearcoat"].default_value = clearcoat
        b.inputs["Clearcoat Roughness"].default_value = 0.06
        if normal is not None:
            self.link(normal, b.inputs["Normal"])
        out = self.node("ShaderNodeOutputMaterial")
        self.link(b.outputs["BSDF"], out.inputs["Surface"])
        return b

    def bump(self, height, strength, distance):
        n = self.node("ShaderNodeBump")
        n.inputs["Strength"].default_value = strength
        n.inputs["Distance"].default_value = distance
        self._in(n.inputs["Height"], height)
        return n.outputs["Normal"]

    def _in(self, socket, v):
        if isinstance(v, bpy.types.NodeSocket):
            self.link(v, socket)
        elif isinstance(v, (tuple, list)):
            socket.default_value = tuple(v) + ((1.0,) if len(socket.default_value) == 4 and len(v) == 3 else ())
        else:
            socket.default_value = v


# --- looks --------------------------------------------------------------------

SURFACES = ("white", "light-grey", "wood", "rubber-mat", "gravel")
LIGHTS = ("softbox", "two-lights", "overcast", "low-sun")
STONES = ("granite", "dolomite", "basalt", "wet")


def plain_material(name, albedo, roughness=0.6):
    mat = bpy.data.materials.new(name)
    n = Nodes(mat)
    n.bsdf(albedo, roughness, specular=0.3)
    return mat


def wood_material(name, rng, coords_scale):
    """Plywood-like: grain lines (wave texture distorted by noise), coords in metres."""
    mat = bpy.data.materials.new(name)
    n = Nodes(mat)
    tc = n.node("ShaderNodeTexCoord").outputs["Object"]
    w = n.node("ShaderNodeTexWave", wave_type="BANDS", bands_direction="X")
    w.inputs["Scale"].default_value = 18.0 * coords_scale
    w.inputs["Distortion"].default_value = 6.0
    w.inputs["Detail"].default_value = 3.0
    n.link(tc, w.inputs["Vector"])
    hue = rng.uniform(-0.04, 0.04)
    col = n.ramp(w.outputs["Fac"], [(0.0, (0.42 + hue, 0.25, 0.11)), (0.55, (0.58 + hue, 0.39, 0.20)),
                                   (1.0, (0.50 + hue, 0.32, 0.15))])
    fine = n.noise(tc, 400.0 * coords_scale, 2.0)
    col = n.mix(n.math("MULTIPLY", fine, 0.25), col, (0.35, 0.21, 0.09))
    n.bsdf(col, 0.45, specular=0.4)
    return mat


def rubber_material(name):
    mat = bpy.data.materials.new(name)
    n = Nodes(mat)
    tc = n.node("ShaderNodeTexCoord").outputs["Object"]
    dimples = n.voronoi(tc, 250.0)  # ~4 mm dimples on a metre-scale object
    n.bsdf((0.035, 0.035, 0.038), 0.85, specular=0.35, normal=n.bump(dimples, 0.35, 0.001))
    return mat


def gravel_material(name):
    """Quarry floor: packed pebbles of varied greys and browns with dust between."""
    mat = bpy.data.materials.new(name)
    n = Nodes(mat)
    tc = n.node("ShaderNodeTexCoord").outputs["Object"]
    cell = n.voronoi(tc, 45.0, out="Color")  # ~2 cm pebbles
    dist = n.voronoi(tc, 45.0)
    tone = n.ramp(cell,
                  [(0.0, (0.20, 0.19, 0.17)), (0.5, (0.42, 0.39, 0.34)), (1.0, (0.55, 0.50, 0.42))])
    grain = n.noise(tc, 900.0, 3.0)
    col = n.mix(n.math("MULTIPLY", grain, 0.35), tone, (0.15, 0.14, 0.12))
    dust = n.math("GREATER_THAN", dist, 0.42)
    col = n.mix(dust, col, (0.30, 0.28, 0.25))
    n.bsdf(col, 0.9, specular=0.25, normal=n.bump(n.math("SUBTRACT", 1.0, dist), 0.6, 0.004))
    return mat


def stone_material(stone, markers, rng):
    """The rock: a procedural stone in the rock's own millimetres, with the
    object markers drawn over it as a person draws them with coloured pencils."""
    mat = bpy.data.materials.new("stone-" + stone)
    n = Nodes(mat)
    p = n.node("ShaderNodeTexCoord").outputs["Object"]  # rock frame, mm
    seed = n.vector((rng.uniform(0, 100), rng.uniform(0, 100), rng.uniform(0, 100)))
    ps = n.vmath("ADD", p, seed)
    tone = n.noise(ps, 1.0 / 18.0, 3.0)       # large-scale tone, ~18 mm
    mottle = n.noise(ps, 1.0 / 4.0, 2.0)      # mottling, ~4 mm
    grains = n.voronoi(ps, 1.0 / 1.1, out="Color")  # mineral grains, ~1 mm
    roughness, specular, clearcoat = 0.6, 0.4, 0.0
    if stone == "granite":
        base = n.ramp(tone, [(0.3, (0.30, 0.29, 0.28)), (0.7, (0.44, 0.43, 0.41))])
        g = n.ramp(grains, [(0.0, (0.06, 0.06, 0.06)), (0.28, (0.06, 0.06, 0.06)), (0.30, (1, 1, 1)),
                            (0.80, (1, 1, 1)), (0.82, (1.7, 1.65, 1.55))])
        col = n.vmath("MULTIPLY", base, g)
        col = n.mix(n.math("MULTIPLY", mottle, 0.35), col, (0.22, 0.21, 0.20))
        roughness = 0.55
    elif stone == "dolomite":
        base = n.ramp(tone, [(0.3, (0.55, 0.45, 0.28)), (0.7, (0.68, 0.58, 0.38))])
        col = n.mix(n.math("MULTIPLY", mottle, 0.4), base, (0.46, 0.37, 0.22))
        g = n.ramp(grains, [(0.0, (0.85, 0.85, 0.85)), (0.5, (1, 1, 1)), (1.0, (1.12, 1.1, 1.05))])
        col = n.vmath("MULTIPLY", col, g)
        roughness = 0.75
    elif stone == "basalt":
        base = n.ramp(tone, [(0.3, (0.055, 0.055, 0.06)), (0.7, (0.09, 0.09, 0.095))])
        g = n.ramp(grains, [(0.0, (0.8, 0.8, 0.8)), (0.85, (1, 1, 1)), (0.87, (2.2, 2.2, 2.1))])
        col = n.vmath("MULTIPLY", base, g)
        col = n.mix(n.math("MULTIPLY", mottle, 0.3), col, (0.13, 0.125, 0.12))
        roughness = 0.5
    elif stone == "wet":
        # A wet granite: darker (water fills the pores) and glossy.
        base = n.ramp(tone, [(0.3, (0.14, 0.135, 0.13)), (0.7, (0.22, 0.21, 0.20))])
        g = n.ramp(grains, [(0.0, (0.3, 0.3, 0.3)), (0.28, (0.3, 0.3, 0.3)), (0.30, (1, 1, 1)),
                            (0.82, (1, 1, 1)), (0.84, (1.6, 1.55, 1.5))])
        col = n.vmath("MULTIPLY", base, g)
        roughness, specular, clearcoat = 0.25, 0.6, 1.0
    else:
        fail("unknown stone '%s' (known: %s)" % (stone, ", ".join(STONES)))
    col = pencil_strokes(n, p, col, markers, rng)
    bump = n.bump(n.noise(ps, 1.0 / 0.7, 2.0), 0.15, 0.3)
    n.bsdf(col, roughness, specular=specular, clearcoat=clearcoat, normal=bump)
    return mat


def pencil_strokes(n, p, col, markers, rng):
    """Paints each head-gap-tail marker pattern over `col` as coloured pencil:
    the band is the sim's (projected along the marker's normal onto the rock),
    but its centre line bows and wanders by up to ~1 mm, its width varies by
    +-25 %, the ends are ragged and the pencil leaves the stone's grain showing."""
    geo_n = n.node("ShaderNodeNewGeometry").outputs["Normal"]
    vt = n.node("ShaderNodeVectorTransform", vector_type="NORMAL", convert_from="WORLD", convert_to="OBJECT")
    n.link(geo_n, vt.inputs["Vector"])
    normal_obj = n.vmath("NORMALIZE", vt.outputs["Vector"])
    for m in markers:
        o, a, nm = Vector(m["origin"]), Vector(m["axis"]), Vector(m["normal"])
        side = nm.cross(a)
        d = n.vmath("SUBTRACT", p, tuple(o))
        along = n.math("ADD", n.vmath("DOT_PRODUCT", d, tuple(a)),
                       (m["head_mm"] + m["gap_mm"] + m["tail_mm"]) / 2.0)
        across = n.vmath("DOT_PRODUCT", d, tuple(side))
        height = n.vmath("DOT_PRODUCT", d, tuple(nm))
        facing = n.vmath("DOT_PRODUCT", normal_obj, tuple(nm))
        # The hand's line: a bow over the pattern's length plus a slow wander.
        length = m["head_mm"] + m["gap_mm"] + m["tail_mm"]
        bow = rng.uniform(-1.0, 1.0) * 4.0 / (length * length)
        centred = n.math("SUBTRACT", along, length / 2.0)
        wander_in = n.node("ShaderNodeCombineXYZ")
        n.link(along, wander_in.inputs[0])
        wander_in.inputs[1].default_value = rng.uniform(0, 50)
        wander = n.math("MULTIPLY", n.math("SUBTRACT", n.noise(wander_in.outputs[0], 0.12, 1.0), 0.5), 1.6)
        offset = n.math("ADD", n.math("MULTIPLY", n.math("MULTIPLY", centred, centred), bow), wander)
        dist = n.math("ABSOLUTE", n.math("SUBTRACT", across, offset))
        # Width: +-25 % along the stroke (pressure), per stroke a little off.
        width_in = n.node("ShaderNodeCombineXYZ")
        n.link(along, width_in.inputs[0])
        width_in.inputs[1].default_value = rng.uniform(50, 100)
        half = n.math("MULTIPLY", n.math("ADD", n.math("MULTIPLY", n.noise(width_in.outputs[0], 0.3, 1.0), 0.5), 0.75),
                      m["width_mm"] * rng.uniform(0.45, 0.55))
        in_band = n.math("LESS_THAN", dist, half)
        # Ragged ends: each segment's end moves by up to 1 mm across the band.
        rag = n.math("MULTIPLY", n.math("SUBTRACT", n.noise(n.vmath("MULTIPLY", d, (0.8, 0.8, 0.8)), 1.0, 1.0), 0.5), 2.0)
        a_r = n.math("ADD", along, rag)
        h0, h1 = 0.0, m["head_mm"]
        t0, t1 = m["head_mm"] + m["gap_mm"], length
        head = n.math("MULTIPLY", n.math("GREATER_THAN", a_r, h0), n.math("LESS_THAN", a_r, h1))
        tail = n.math("MULTIPLY", n.math("GREATER_THAN", a_r, t0), n.math("LESS_THAN", a_r, t1))
        seg = n.math("MAXIMUM", head, tail)
        near = n.math("LESS_THAN", n.math("ABSOLUTE", height), 12.0)
        faces = n.math("GREATER_THAN", facing, 0.3)
        cover = n.math("MULTIPLY", n.math("MULTIPLY", in_band, seg), n.math("MULTIPLY", near, faces))
        # Pencil grain: the stone's high points take the colour, its pits less.
        grain = n.noise(n.vmath("MULTIPLY", d, (3.0, 3.0, 3.0)), 1.0, 2.0)
        strength = n.math("MULTIPLY", cover, n.math("ADD", n.math("MULTIPLY", grain, 0.35), 0.62), clamp=True)
        alb = m["albedo"]
        tint = rng.uniform(0.9, 1.1)
        pencil = (min(1.0, alb[0] * tint), min(1.0, alb[1] * tint), min(1.0, alb[2] * tint))
        col = n.mix(strength, col, pencil)
    return col


def build_lights(kind, rng, cam_pos, target):
    world = bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    sky = 0.04

    def area(name, azimuth_deg, elevation_deg, dist_m, size_m, power_w):
        light = bpy.data.lights.new(name, "AREA")
        light.shape = "SQUARE"
        light.size = size_m
        light.energy = power_w
        obj = bpy.data.objects.new(name, light)
        bpy.context.scene.collection.objects.link(obj)
        az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
        pos = target + Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))) * dist_m
        obj.location = pos
        obj.rotation_euler = (target - pos).to_track_quat("-Z", "Y").to_euler()

    # Azimuths relative to the camera's, so a look is lit the same whatever
    # the rig's orientation.
    cam_az = math.degrees(math.atan2(cam_pos.y - target.y, cam_pos.x - target.x))
    if kind == "softbox":
        area("softbox", cam_az + rng.uniform(25, 45), rng.uniform(50, 65), 0.9, 0.6, 60.0)
    elif kind == "two-lights":
        area("key", cam_az + rng.uniform(40, 60), rng.uniform(40, 55), 0.8, 0.35, 45.0)
        area("fill", cam_az - rng.uniform(60, 90), rng.uniform(30, 45), 1.0, 0.35, 25.0)
    elif kind == "overcast":
        sky = 1.0
    elif kind == "low-sun":
        sun = bpy.data.lights.new("sun", "SUN")
        sun.energy = 3.0
        sun.angle = math.radians(0.53)  # the sun's disc: hard shadows
        obj = bpy.data.objects.new("sun", sun)
        bpy.context.scene.collection.objects.link(obj)
        az, el = math.radians(cam_az + rng.uniform(60, 120) * rng.choice((-1, 1))), math.radians(rng.uniform(12, 20))
        d = Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
        obj.rotation_euler = (-d).to_track_quat("-Z", "Y").to_euler()
        sky = 0.35
    else:
        fail("unknown light '%s' (known: %s)" % (kind, ", ".join(LIGHTS)))
    bg.inputs["Color"].default_value = (0.85, 0.9, 1.0, 1.0) if kind in ("overcast", "low-sun") else (1, 1, 1, 1)
    bg.inputs["Strength"].default_value = sky


# --- scene --------------------------------------------------------------------


def add_object(name, mesh, material=None, parent=None):
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    if material is not None:
        obj.data.materials.append(material)
    if parent is not None:
        obj.parent = parent
    return obj


def disc_mesh(radius_m, thickness_m, segments=256):
    """Closed cylinder, top face at z = 0."""
    mesh = bpy.data.meshes.new("disc")
    verts, faces = [], []
    for i in range(segments):
        t = 2 * math.pi * i / segments
        verts.append((radius_m * math.cos(t), radius_m * math.sin(t), 0.0))
        verts.append((radius_m * math.cos(t), radius_m * math.sin(t), -thickness_m))
    for i in range(segments):
        j = (i + 1) % segments
        faces.append((2 * i, 2 * i + 1, 2 * j + 1, 2 * j))
    faces.append(tuple(2 * i for i in range(segments)))
    faces.append(tuple(2 * i + 1 for i in reversed(range(segments))))
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    return mesh


def rect_mesh(name, hx, hy, z):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-hx, -hy, z), (hx, -hy, z), (hx, hy, z), (-hx, hy, z)], [], [(0, 1, 2, 3)])
    mesh.uv_layers.new()
    uv = mesh.uv_layers[0].data
    for i, (u, v) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
        uv[i].uv = (u, v)
    mesh.update()
    return mesh


def rock_mesh(rock):
    verts = rock["vertices"]
    faces = rock["faces"]
    if len(verts) % 3 or len(faces) % 3 or not faces:
        fail("rock mesh: vertices and faces must be flat lists of triples")
    mesh = bpy.data.meshes.new("rock")
    mesh.from_pydata([verts[i:i + 3] for i in range(0, len(verts), 3)], [],
                     [faces[i:i + 3] for i in range(0, len(faces), 3)])
    mesh.validate()
    mesh.update()
    # Smooth within facets, sharp over real edges (a quarried stone's ridges).
    mesh.use_auto_smooth = True
    mesh.auto_smooth_angle = math.radians(35)
    for poly in mesh.polygons:
        poly.use_smooth = True
    return mesh


def board_material(scene_dir, board):
    mat = bpy.data.materials.new("board")
    n = Nodes(mat)
    img = bpy.data.images.load(os.path.join(scene_dir, board["image"]))
    img.colorspace_settings.name = "Non-Color"
    tex = n.node("ShaderNodeTexImage", interpolation="Linear", extension="EXTEND")
    tex.image = img
    uv = n.node("ShaderNodeTexCoord").outputs["UV"]
    # UV 0..1 over the paper; the squares area is the middle, margin around it.
    w, h, mg = board["width_mm"], board["height_mm"], board["paper_margin_mm"]
    scale = n.node("ShaderNodeMapping")
    scale.inputs["Scale"].default_value = ((w + 2 * mg) / w, (h + 2 * mg) / h, 1.0)
    scale.inputs["Location"].default_value = (-mg / w, -mg / h, 0.0)
    n.link(uv, scale.inputs["Vector"])
    n.link(scale.outputs["Vector"], tex.inputs["Vector"])
    # Printed value v (0 ink .. 1 paper) as albedo, paper outside the squares.
    ink, paper = board["ink_albedo"], board["paper_albedo"]
    val = n.math("ADD", n.math("MULTIPLY", tex.outputs["Color"], paper - ink), ink)
    uvs = n.node("ShaderNodeSeparateXYZ")
    n.link(scale.outputs["Vector"], uvs.inputs[0])
    inside = n.math("MULTIPLY",
                    n.math("MULTIPLY", n.math("GREATER_THAN", uvs.outputs[0], 0.0), n.math("LESS_THAN", uvs.outputs[0], 1.0)),
                    n.math("MULTIPLY", n.math("GREATER_THAN", uvs.outputs[1], 0.0), n.math("LESS_THAN", uvs.outputs[1], 1.0)))
    a = n.mix(inside, (paper, paper, paper), val)
    n.bsdf(a, 0.7, specular=0.3)
    return mat


def build_scene(scene_dir, s):
    look = s["look"]
    rng = random.Random(look.get("seed", 1))
    cam_s = s["camera"]
    W, H = cam_s["width"], cam_s["height"]
    fx, fy, cx, cy = cam_s["fx"], cam_s["fy"], cam_s["cx"], cam_s["cy"]
    if abs(fx - fy) > 1e-6 * fx:
        fail("the camera's fx and fy differ; this renderer draws square pixels only")

    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    scene = bpy.context.scene

    # Camera: OpenCV world->camera to a Blender camera object.
    w2c = mm_to_m(matrix4(cam_s["world_to_camera_4x4"]))
    c2w = w2c.inverted() @ Matrix.Diagonal((1.0, -1.0, -1.0, 1.0))
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = 36.0
    cam_data.lens = fx * 36.0 / W
    # Principal point: Blender's is the frame's centre moved by the shift, in
    # units of the larger side; OpenCV's pixel centres are at integers.
    cam_data.shift_x = (W / 2.0 - (cx + 0.5)) / max(W, H)
    cam_data.shift_y = ((cy + 0.5) - H / 2.0) / max(W, H)
    cam_data.clip_start = 0.01
    cam_data.clip_end = 100.0
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    cam.matrix_world = c2w
    scene.camera = cam

    # Disc (top at z = 0, turning about z), its labels and board; the floor below.
    surface = look["surface"]
    if surface not in SURFACES:
        fail("unknown surface '%s' (known: %s)" % (surface, ", ".join(SURFACES)))
    radius = s["disc"]["radius_mm"] * MM
    thick = s["disc"]["thickness_mm"] * MM
    disc_mats = {
        "white": lambda: plain_material("disc", (0.80, 0.80, 0.79)),
        "light-grey": lambda: plain_material("disc", (0.55, 0.55, 0.56)),
        "wood": lambda: wood_material("disc", rng, 1.0),
        "rubber-mat": lambda: rubber_material("disc"),
        "gravel": lambda: plain_material("disc", (0.55, 0.55, 0.56)),
    }
    floor_mats = {
        "white": lambda: plain_material("floor", (0.85, 0.85, 0.85)),
        "light-grey": lambda: plain_material("floor", (0.45, 0.45, 0.46)),
        "wood": lambda: wood_material("floor", rng, 0.5),
        "rubber-mat": lambda: plain_material("floor", (0.10, 0.10, 0.10), 0.8),
        "gravel": lambda: gravel_material("floor"),
    }
    platter = bpy.data.objects.new("platter", None)
    scene.collection.objects.link(platter)
    disc = add_object("disc", disc_mesh(radius, thick), disc_mats[surface](), platter)
    rim = add_object("rim-floor", rect_mesh("floor", 10.0, 10.0, -thick), floor_mats[surface]())
    rim.name = "floor"
    for lb in s.get("labels", []):
        half = lb["size_mm"] / 2.0 * MM
        label = add_object("label-" + lb["color"], rect_mesh("label", half, half, 0.0002),
                           plain_material("label-" + lb["color"], lb["albedo"], 0.5), platter)
        label.location = (lb["x_mm"] * MM, lb["y_mm"] * MM, 0.0)
    if s.get("board"):
        b = s["board"]
        hx = (b["width_mm"] / 2.0 + b["paper_margin_mm"]) * MM
        hy = (b["height_mm"] / 2.0 + b["paper_margin_mm"]) * MM
        paper = add_object("board", rect_mesh("board", hx, hy, 0.0003), board_material(scene_dir, b), platter)
        paper.location = (b["x_mm"] * MM, b["y_mm"] * MM, 0.0)
        paper.rotation_euler = (0.0, 0.0, math.radians(b["yaw_deg"]))

    rock = None
    if s.get("rock"):
        stone = look["stone"]
        with open(os.path.join(scene_dir, s["rock"]["mesh"])) as f:
            mesh = rock_mesh(json.load(f))
        rock = add_object("rock", mesh, stone_material(stone, s["rock"].get("markers", []), rng))
        rock.pass_index = 1

    target = Vector((0.0, 0.0, 0.04))
    build_lights(look["light"], rng, c2w.translation, target)

    # Render settings: Cycles on the CPU, a fixed sample count, Cycles' own
    # denoiser off (not in Debian's build; see denoise.py for ours).
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(s["render"].get("samples", 16))
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 6
    scene.cycles.diffuse_bounces = 3
    scene.cycles.glossy_bounces = 2
    scene.cycles.transmission_bounces = 0
    scene.cycles.transparent_max_bounces = 2
    scene.cycles.caustics_reflective = False
    scene.cycles.caustics_refractive = False
    scene.cycles.sample_clamp_indirect = 10.0
    scene.cycles.seed = look.get("seed", 1)
    threads = int(s["render"].get("threads", 0))
    if threads > 0:
        r.threads_mode = "FIXED"
        r.threads = threads
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_border = False
    r.film_transparent = False
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.image_settings.color_depth = "8"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.gamma = 1.0
    scene.sequencer_colorspace_settings.name = "sRGB"

    # The rock's silhouette: object index pass -> ID mask -> a file per view.
    scene.view_layers[0].use_pass_object_index = True
    scene.use_nodes = True
    tree = scene.node_tree
    tree.nodes.clear()
    rl = tree.nodes.new("CompositorNodeRLayers")
    comp = tree.nodes.new("CompositorNodeComposite")
    tree.links.new(rl.outputs["Image"], comp.inputs["Image"])
    mask_out = None
    if rock is not None:
        idm = tree.nodes.new("CompositorNodeIDMask")
        idm.index = 1
        idm.use_antialiasing = False
        tree.links.new(rl.outputs["IndexOB"], idm.inputs["ID value"])
        mask_out = tree.nodes.new("CompositorNodeOutputFile")
        mask_out.format.file_format = "PNG"
        mask_out.format.color_mode = "BW"
        mask_out.format.color_depth = "8"
        tree.links.new(idm.outputs["Alpha"], mask_out.inputs[0])
    passes_out = None
    if s["render"].get("denoise", False):
        passes_out = denoise.add_pass_output(scene, tree, rl, os.path.join(scene_dir, "passes"))
    return scene, platter, rock, disc, mask_out, passes_out


def auto_exposure(scene, scene_dir, platter, rock, disc, view):
    """The exposure an operator sets with a white card: with the rock away and
    a white diffuse card (albedo 0.9) over the disc, the middle of the frame
    (the disc's centre) renders at 0.75 of white, so that paper, labels and a
    pale stone do not clip, and a dark stone on a dark mat stays dark."""
    pose(platter, rock, view)
    r = scene.render
    saved = (r.resolution_percentage, scene.cycles.samples, r.image_settings.file_format,
             r.image_settings.color_depth, r.image_settings.color_mode)
    disc_mat = disc.material_slots[0].material
    disc.material_slots[0].material = plain_material("white-card", (0.9, 0.9, 0.9), 0.9)
    if rock is not None:
        rock.hide_render = True
    r.resolution_percentage = 25
    scene.cycles.samples = 16
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_depth = "32"
    r.image_settings.color_mode = "RGB"
    scene.view_settings.exposure = 0.0
    path = os.path.join(scene_dir, "exposure-probe.exr")
    r.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path)
    w, h = img.size
    px = img.pixels[:]
    lum = []
    for y in range(int(0.4 * h), int(0.6 * h)):
        for x in range(int(0.4 * w), int(0.6 * w)):
            i = 4 * (y * w + x)
            lum.append(0.2126 * px[i] + 0.7152 * px[i + 1] + 0.0722 * px[i + 2])
    bpy.data.images.remove(img)
    os.remove(path)
    (r.resolution_percentage, scene.cycles.samples, r.image_settings.file_format, r.image_settings.color_depth,
     r.image_settings.color_mode) = saved
    disc.material_slots[0].material = disc_mat
    if rock is not None:
        rock.hide_render = False
    lum.sort()
    median = lum[len(lum) // 2] if lum else 0.0
    if median <= 0:
        fail("the exposure probe rendered the white card black; check the lights")
    return math.log2(0.75 / median)


def pose(platter, rock, view):
    platter.matrix_world = Matrix.Rotation(math.radians(view["platter_deg"]), 4, "Z")
    if rock is not None:
        rock.matrix_world = mm_to_m(matrix4(view["rock_to_world_4x4"])) @ Matrix.Diagonal((MM, MM, MM, 1.0))


class FrameRenderer:
    """Renders the scene's current pose to an 8-bit PNG: Cycles' frame as it
    comes, or (with the passes' output node build_scene added for
    render.denoise) two half-sample renders through denoise.py with a
    camera's noise put in."""

    def __init__(self, scene, passes_out, s, exposure):
        self.scene = scene
        self.on = passes_out is not None
        self.tmp = passes_out.base_path if self.on else None
        self.samples = scene.cycles.samples
        self.seed = scene.cycles.seed
        self.sigma = float(s["render"].get("camera_noise_levels", 2.0))
        self.exposure = exposure
        self.rng = np.random.default_rng(self.seed)
        self.count = 0

    def render(self, path):
        sc = self.scene
        sc.render.filepath = path
        if not self.on:
            bpy.ops.render.render(write_still=True)
            return
        half = max(1, (self.samples + 1) // 2)
        w, h = sc.render.resolution_x, sc.render.resolution_y
        runs = []
        for k in range(2):
            sc.cycles.samples = half
            sc.cycles.seed = self.seed + 7919 * (2 * self.count + k + 1)
            bpy.ops.render.render(write_still=False)
            runs.append(denoise.load_passes(self.tmp, w, h))
        sc.cycles.samples, sc.cycles.seed = self.samples, self.seed
        self.count += 1
        lin = denoise.combine(runs[0], runs[1], self.sigma, self.exposure, self.rng)
        denoise.save_png(sc, lin, path)


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) != 1:
        fail("usage: blender -b --python render_capture.py -- SCENE_DIR")
    scene_dir = argv[0]
    try:
        with open(os.path.join(scene_dir, "scene.json")) as f:
            s = json.load(f)
    except (OSError, ValueError) as e:
        fail("cannot read %s/scene.json: %s" % (scene_dir, e))
    if s.get("format") != "aggscan-blender-scene-1":
        fail("scene.json is not an aggscan-blender-scene-1 file")
    views = s.get("views", [])
    if not views:
        fail("scene.json has no views")
    scene, platter, rock, disc, mask_out, passes_out = build_scene(scene_dir, s)
    exposure = s["render"].get("exposure")
    if exposure is None:
        exposure = auto_exposure(scene, scene_dir, platter, rock, disc, views[0])
    scene.view_settings.exposure = exposure
    frames = FrameRenderer(scene, passes_out, s, exposure)
    times = []
    for v in views:
        pose(platter, rock, v)
        image = os.path.join(scene_dir, v["image"])
        os.makedirs(os.path.dirname(image), exist_ok=True)
        if mask_out is not None:
            mask = os.path.join(scene_dir, v["mask"])
            mask_out.base_path = os.path.dirname(mask)
            mask_out.file_slots[0].path = os.path.basename(mask)[:-len(".png")] + "-frame"
        scene.frame_set(1)
        t0 = time.monotonic()
        frames.render(image)
        times.append(time.monotonic() - t0)
        if mask_out is not None:
            os.replace(os.path.join(os.path.dirname(mask), os.path.basename(mask)[:-len(".png")] + "-frame0001.png"),
                       mask)
        print("render_capture.py: side %d view %d rendered in %.2f s" % (v["side"], v["view"], times[-1]), flush=True)
        if v.get("empty_image") and rock is not None:
            # The same view with the rock taken away: the environment's
            # empty-turntable photo (disc at this angle, same lights and
            # exposure), for teaching the mask network a new environment.
            rock.hide_render = True
            empty = os.path.join(scene_dir, v["empty_image"])
            os.makedirs(os.path.dirname(empty), exist_ok=True)
            if mask_out is not None:
                mask_out.mute = True
            frames.render(empty)
            if mask_out is not None:
                mask_out.mute = False
                stray = os.path.join(mask_out.base_path, mask_out.file_slots[0].path + "0001.png")
                if os.path.exists(stray):
                    os.remove(stray)
            rock.hide_render = False
    if frames.on and os.path.isdir(frames.tmp) and not os.listdir(frames.tmp):
        os.rmdir(frames.tmp)
    report = {
        "renderer": "blender " + bpy.app.version_string + " cycles cpu",
        "samples": scene.cycles.samples,
        "denoise": frames.on,
        "exposure_ev": exposure,
        "width": scene.render.resolution_x,
        "height": scene.render.resolution_y,
        "frame_seconds": times,
        "mean_frame_seconds": sum(times) / len(times),
    }
    with open(os.path.join(scene_dir, "render_report.json"), "w") as f:
        json.dump(report, f, indent=1)


main()
