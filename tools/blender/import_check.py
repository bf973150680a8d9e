"""Checks that Blender imports a world exported by `mwb export` (.glb) as exported.

Run (Blender 3.4, e.g. Debian's `apt-get install blender python3-numpy`; the glTF add-on
needs numpy):

    target/release/mwb export --scene tumble --seed 42 --out /tmp/w.glb
    blender -b --factory-startup --python tools/blender/import_check.py -- /tmp/w.glb [--stride N]

Several .glb paths may follow `--`. Exit code 0 when every file passes, 1 when one does not
(every mismatch is printed), 2 without a path.

What it checks, against the .glb's own JSON and binary chunks (read here with `struct`, not by
Blender), after `bpy.ops.import_scene.gltf` into an empty scene whose frame rate is the
world's (1 / the animation's key spacing, so key k lands on frame k):

* every node of the file (the world's root, each static, each body, named as in the scene)
  is an object of that name, and every node with a mesh is a mesh object;
* every animated body has an action whose location (3) and rotation (4) F-curves hold one
  key per exported key, from frame 0 to frame (keys - 1);
* at every `--stride`-th key (default 1: every key) and at the last one, each animated
  body's evaluated world location equals the exported translation converted from glTF's
  y-up to Blender's z-up, (x, y, z) -> (x, -z, y), within 1e-4 m, and its world rotation
  equals the exported quaternion converted the same way, within 1e-4 (up to sign).
"""

import json
import math
import struct
import sys

import bpy
from mathutils import Quaternion, Vector

# Blender 3.4's glTF add-on still uses `np.bool` (on its default "Shading: Use Normal Data"
# path), an alias NumPy 1.24 removed (Debian 12 ships Blender 3.4.1 with NumPy 1.24.2): every
# import of a mesh with normals fails with "module 'numpy' has no attribute 'bool'". Fixed
# upstream in Blender 3.5 (KhronosGroup/glTF-Blender-IO#1831, #1844). Restore the alias here;
# interactively, choose Shading "Flat Shading" or "Smooth Shading" in the import dialog.
import numpy

if "bool" not in numpy.__dict__:
    numpy.bool = bool
    print("import_check: numpy.bool restored for Blender 3.4's glTF add-on (NumPy >= 1.24)")

POS_TOL = 1e-4  # m; the file holds f32 (the bodies stay within ~1e3 m)
ROT_TOL = 1e-4


def read_glb(path):
    """(json dict, bin bytes) of a .glb."""
    data = open(path, "rb").read()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or length != len(data):
        raise ValueError(f"{path}: not a glTF 2.0 binary of {len(data)} bytes")
    off, doc, binary = 12, None, b""
    while off < length:
        clen, ctype = struct.unpack_from("<II", data, off)
        chunk = data[off + 8 : off + 8 + clen]
        if ctype == 0x4E4F534A:  # JSON
            doc = json.loads(chunk)
        elif ctype == 0x004E4942:  # BIN
            binary = chunk
        off += 8 + clen
    if doc is None:
        raise ValueError(f"{path}: no JSON chunk")
    return doc, binary


def accessor_floats(doc, binary, index):
    """The f32 values of accessor `index`, as a list of tuples (or floats for SCALAR)."""
    acc = doc["accessors"][index]
    if acc["componentType"] != 5126:
        raise ValueError(f"accessor {index}: component type {acc['componentType']}, not f32")
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", 4 * width)
    out = []
    for i in range(acc["count"]):
        v = struct.unpack_from(f"<{width}f", binary, start + i * stride)
        out.append(v[0] if width == 1 else v)
    return out


def check(path, stride):
    """Problems found importing `path` (an empty list when it passes)."""
    problems = []
    doc, binary = read_glb(path)
    anims = doc.get("animations", [])
    if len(anims) != 1:
        return [f"expected one animation in the file, found {len(anims)}"]
    anim = anims[0]
    # Per animated node: (times, translations, rotations).
    tracks = {}
    for ch in anim["channels"]:
        sampler = anim["samplers"][ch["sampler"]]
        node = ch["target"]["node"]
        times = accessor_floats(doc, binary, sampler["input"])
        values = accessor_floats(doc, binary, sampler["output"])
        t = tracks.setdefault(node, {})
        t["times"] = times
        t[ch["target"]["path"]] = values
    times = next(iter(tracks.values()))["times"]
    keys = len(times)
    if keys < 2:
        return [f"the animation has {keys} keys"]
    dt = times[1] - times[0]
    fps = round(1.0 / dt)
    if abs(fps * dt - 1.0) > 1e-5:
        return [f"key spacing {dt} s is not 1/integer: frames would not be whole"]

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = fps
    scene.render.fps_base = 1.0
    result = bpy.ops.import_scene.gltf(filepath=path)
    if "FINISHED" not in result:
        return [f"import_scene.gltf returned {result}"]

    # Names and meshes.
    nodes = doc["nodes"]
    objects = {}
    for i, n in enumerate(nodes):
        name = n.get("name")
        obj = bpy.data.objects.get(name) if name else None
        if obj is None:
            problems.append(f"node {i} {name!r}: no object of that name")
            continue
        objects[i] = obj
        if "mesh" in n and obj.type != "MESH":
            problems.append(f"{name!r}: a {obj.type} object, not a mesh")
    extra = len(bpy.data.objects) - len(nodes)
    if extra != 0:
        problems.append(f"{len(bpy.data.objects)} objects for {len(nodes)} nodes")

    # Actions: one key per exported key.
    for i, tr in tracks.items():
        obj = objects.get(i)
        if obj is None:
            continue
        ad = obj.animation_data
        action = ad.action if ad else None
        if action is None:
            problems.append(f"{obj.name!r}: no action")
            continue
        for data_path, count in (("location", 3), ("rotation_quaternion", 4)):
            curves = [fc for fc in action.fcurves if fc.data_path == data_path]
            if len(curves) != count:
                problems.append(f"{obj.name!r}: {len(curves)} {data_path} curves, not {count}")
            for fc in curves:
                pts = fc.keyframe_points
                if len(pts) != keys:
                    problems.append(
                        f"{obj.name!r} {data_path}[{fc.array_index}]: "
                        f"{len(pts)} keys, exported {keys}"
                    )
                elif abs(pts[0].co[0]) > 1e-3 or abs(pts[-1].co[0] - (keys - 1)) > 1e-3:
                    problems.append(
                        f"{obj.name!r} {data_path}: keys on frames {pts[0].co[0]}..{pts[-1].co[0]},"
                        f" expected 0..{keys - 1}"
                    )

    # Evaluated poses at the keys.
    frames = sorted(set(range(0, keys, max(1, stride))) | {keys - 1})
    worst_pos, worst_rot = 0.0, 0.0
    for k in frames:
        scene.frame_set(k)
        for i, tr in tracks.items():
            obj = objects.get(i)
            if obj is None:
                continue
            m = obj.matrix_world
            if "translation" in tr:
                x, y, z = tr["translation"][k]
                want = Vector((x, -z, y))
                err = (m.translation - want).length
                worst_pos = max(worst_pos, err)
                if err > POS_TOL:
                    problems.append(
                        f"{obj.name!r} frame {k}: location {tuple(m.translation)}, "
                        f"exported {tuple(want)} (off by {err:.3g} m)"
                    )
            if "rotation" in tr:
                qx, qy, qz, qw = tr["rotation"][k]
                want = Quaternion((qw, qx, -qz, qy)).normalized()
                got = m.to_quaternion().normalized()
                # |got - ±want|: about half the angle between them (rad), well conditioned.
                err = min(
                    math.sqrt(sum((g - sign * w) ** 2 for g, w in zip(got, want)))
                    for sign in (1.0, -1.0)
                )
                worst_rot = max(worst_rot, err)
                if err > ROT_TOL:
                    problems.append(
                        f"{obj.name!r} frame {k}: rotation {tuple(got)}, exported {tuple(want)}"
                    )
    print(
        f"{path}: {len(nodes)} nodes, {len(tracks)} animated bodies, {keys} keys at {fps} "
        f"frames/s; checked {len(frames)} frames; worst location error {worst_pos:.2e} m, "
        f"worst rotation error {worst_rot:.2e}"
    )
    return problems


def main():
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else []
    stride = 1
    paths = []
    it = iter(argv)
    for a in it:
        if a == "--stride":
            stride = int(next(it))
        else:
            paths.append(a)
    if not paths:
        print(__doc__)
        sys.exit(2)
    failed = False
    for path in paths:
        try:
            problems = check(path, stride)
        except Exception as e:  # a file that cannot be read or imported fails the check
            problems = [f"{type(e).__name__}: {e}"]
        for p in problems[:50]:
            print(f"{path}: MISMATCH {p}")
        if len(problems) > 50:
            print(f"{path}: ... and {len(problems) - 50} more")
        print(f"{path}: {'FAIL' if problems else 'OK'}")
        failed |= bool(problems)
    sys.exit(1 if failed else 0)


main()
