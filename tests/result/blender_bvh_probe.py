"""Import a BVH file with Blender's own importer (default options) and print what Blender made of it.

Run in a Python that has the ``bpy`` package (tests/result/conftest.py finds or builds one)::

    python blender_bvh_probe.py FILE.bvh FRAME [FRAME ...]

Prints one JSON object: ``bones`` (names, in the armature's order), ``parents`` (the
parent bone's name or null), ``rest_heads`` (each bone's head in world coordinates in
the rest pose, from the armature's rest bones), ``frame_range`` (the imported action's
first and last frame) and ``heads`` (per asked frame, each bone's head in world
coordinates in the pose at that frame). Blender units as imported: the importer's default
scale is 1 and its default axes map the file's (x, y, z) to Blender's (x, -z, y).
"""

from __future__ import annotations

import json
import sys

import bpy


def world(obj, vector) -> list[float]:
    return list(obj.matrix_world @ vector)


def main(path: str, frames: list[int]) -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=path)  # the importer's defaults: axes, scale, frame start 1
    arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    bones = list(arm.data.bones)
    action = arm.animation_data.action
    out = {
        "bones": [b.name for b in bones],
        "parents": [b.parent.name if b.parent else None for b in bones],
        "rest_heads": [world(arm, b.head_local) for b in bones],
        "rest_tails": [world(arm, b.tail_local) for b in bones],
        "frame_range": [float(v) for v in action.frame_range],
        "heads": {},
    }
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        bpy.context.view_layer.update()
        out["heads"][str(frame)] = [world(arm, arm.pose.bones[b.name].head) for b in bones]
    return out


if __name__ == "__main__":
    print("PROBE-JSON " + json.dumps(main(sys.argv[1], [int(v) for v in sys.argv[2:]])))
