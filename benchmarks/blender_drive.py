"""Keyframes or a Transform Cache: how the Blender extension should drive the objects.

For N cubes (one shared mesh) and a baked USD of F frames (xforms layout, every body
moving every frame), in Blender as a Python module (bpy), two ways to put the bake
on the objects:

keys    the extension's way (blender/dempipe_bake/apply.py): one action per object,
        location / quaternion / scale keyed at every frame;
cache   a Transform Cache constraint per object on the USD (Blender's CacheFile),
        object_path = the body prim.

Measured per way: the time to set it up, the .blend's size (plus the USD the cache
reads), the time to open the .blend again, and the time per frame of scrubbing
(``scene.frame_set`` over every frame, after one pass to warm). Each way runs in a
fresh process. Results as a Markdown table (docs/blender.md).

    python benchmarks/blender_drive.py                 # 1,000 and 10,000 objects
    python benchmarks/blender_drive.py --counts 200 --frames 24
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _side(n: int) -> int:
    """Bodies along each edge of the cube they start in."""
    side = 1
    while side ** 3 < n:
        side += 1
    return side


def write_usd(path: Path, n: int, frames: int) -> None:
    """A bake-like USD: /World/Bodies/b_<i>/b_<i>_0, translate and orient at every
    frame (a fall with a spin), as dempipe's xforms layout writes a scene from the
    extension (a group of one body per object)."""
    import numpy as np
    from pxr import Gf, Sdf, Vt

    layer = Sdf.Layer.CreateNew(str(path))
    layer.startTimeCode, layer.endTimeCode = 1, frames
    layer.timeCodesPerSecond = layer.framesPerSecond = 24
    world = Sdf.PrimSpec(layer, "World", Sdf.SpecifierDef, "Xform")
    bodies = Sdf.PrimSpec(world, "Bodies", Sdf.SpecifierDef, "Xform")
    side = _side(n)
    idx = np.arange(n)
    base = np.stack([idx % side, (idx // side) % side, idx // side ** 2], axis=1) * 0.3
    t = np.arange(frames) / 24.0
    with Sdf.ChangeBlock():
        for i in range(n):
            group = Sdf.PrimSpec(bodies, f"b_{i}", Sdf.SpecifierDef, "Xform")
            prim = Sdf.PrimSpec(group, f"b_{i}_0", Sdf.SpecifierDef, "Xform")
            tr = Sdf.AttributeSpec(prim, "xformOp:translate", Sdf.ValueTypeNames.Double3)
            ori = Sdf.AttributeSpec(prim, "xformOp:orient", Sdf.ValueTypeNames.Quatf)
            order = Sdf.AttributeSpec(prim, "xformOpOrder", Sdf.ValueTypeNames.TokenArray,
                                      variability=Sdf.VariabilityUniform)
            order.default = Vt.TokenArray(["xformOp:translate", "xformOp:orient"])
            for f in range(frames):
                x = base[i] + [0.0, 0.0, -4.9 * t[f] ** 2]
                a = 0.5 * (1 + i % 7) * t[f]
                layer.SetTimeSample(tr.path, f + 1, tuple(float(c) for c in x))
                layer.SetTimeSample(ori.path, f + 1, Gf.Quatf(float(np.cos(a)), 0.0, 0.0,
                                                             float(np.sin(a))))
    layer.Save()


CHILD = r"""
import json, sys, time
from pathlib import Path
way, n, frames, usd, blend = sys.argv[-5], int(sys.argv[-4]), int(sys.argv[-3]), sys.argv[-2], sys.argv[-1]
sys.path.insert(0, str(Path(sys.argv[-6]) / "blender"))
import bpy
from dempipe_bake import apply

def scrub(scene):
    for f in range(1, frames + 1):
        scene.frame_set(f)
    t0 = time.perf_counter()
    for f in range(1, frames + 1):
        scene.frame_set(f)
    return (time.perf_counter() - t0) / frames

bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.frame_start, scene.frame_end = 1, frames
mesh = bpy.data.meshes.new("cube")
import bmesh
bm = bmesh.new(); bmesh.ops.create_cube(bm, size=0.2); bm.to_mesh(mesh); bm.free()
side = 1
while side ** 3 < n:
    side += 1
for i in range(n):
    ob = bpy.data.objects.new(f"b.{i}", mesh)
    # where the body is at the first frame, as a user's object would be
    ob.location = (0.3 * (i % side), 0.3 * ((i // side) % side), 0.3 * (i // side ** 2))
    scene.collection.objects.link(ob)
t0 = time.perf_counter()
if way == "keys":
    apply.apply_bake(scene, usd, {f"b_{i}": f"b.{i}" for i in range(n)}, {}, 1, frames)
else:
    bpy.ops.cachefile.open(filepath=usd)
    cf = bpy.data.cache_files[-1]
    for i in range(n):
        c = bpy.data.objects[f"b.{i}"].constraints.new("TRANSFORM_CACHE")
        c.cache_file = cf
        c.object_path = f"/World/Bodies/b_{i}/b_{i}_0"
setup = time.perf_counter() - t0
per_frame = scrub(scene)
scene.frame_set(frames)
probe = list(bpy.data.objects["b.1"].matrix_world.translation)
bpy.ops.wm.save_as_mainfile(filepath=blend)
t0 = time.perf_counter()
bpy.ops.wm.open_mainfile(filepath=blend)
load = time.perf_counter() - t0
scene = bpy.context.scene
loaded_per_frame = scrub(scene)
print("BENCH_JSON" + json.dumps(dict(setup=setup, scrub=per_frame, load=load,
                                     scrub_loaded=loaded_per_frame, probe=probe)))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--frames", type=int, default=48)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in args.counts:
            usd = tmp / f"bake_{n}.usdc"
            t0 = time.perf_counter()
            write_usd(usd, n, args.frames)
            print(f"{n} objects: USD written in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
            for way in ("keys", "cache"):
                blend = tmp / f"{way}_{n}.blend"
                proc = subprocess.run([sys.executable, "-c", CHILD, str(ROOT), way, str(n),
                                       str(args.frames), str(usd), str(blend)],
                                      capture_output=True, text=True, timeout=3600)
                if proc.returncode:
                    raise SystemExit(proc.stderr[-3000:])
                line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("BENCH_JSON"))
                r = json.loads(line[len("BENCH_JSON"):])
                r.update(way=way, n=n, blend_mb=blend.stat().st_size / 2**20,
                         usd_mb=usd.stat().st_size / 2**20 if way == "cache" else 0.0)
                rows.append(r)
                print(json.dumps(r), file=sys.stderr)
    print("| objects | way | set up [s] | .blend [MiB] | + USD [MiB] | open [s] | "
          "scrub [ms/frame] | scrub after open [ms/frame] |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']:,} | {r['way']} | {r['setup']:.2f} | {r['blend_mb']:.1f} | "
              f"{r['usd_mb']:.1f} | {r['load']:.2f} | {1e3 * r['scrub']:.1f} | "
              f"{1e3 * r['scrub_loaded']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
