"""`dempipe preview`: pictures of real bakes, checked against the USD.

A tiny scene (a box, a ball and a cylinder of distinct colours dropped on a plane) is baked
in both layouts; its pictures must show each body's colour where the camera projects the
centre the USD gives, change where the bodies moved, and agree between the layouts.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from dempipe.pipeline.bake import bake

pytest.importorskip("moderngl")
pytest.importorskip("PIL")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade  # noqa: E402

from dempipe import preview  # noqa: E402

SCENE = """
[output]
fps = 24
duration = 0.25
up_axis = "Z"

[simulation]
resolution = 4
seed = 1

[materials.wood]
density = 700.0
restitution = 0.3
friction = 0.5

[shapes.cube]
builtin = "box"
[shapes.ball]
builtin = "sphere"
[shapes.can]
builtin = "cylinder"

[[bodies]]
name = "cube"
shape = "cube"
layout = "single"
position = [-0.09, 0.0, 0.09]

[[bodies]]
name = "ball"
shape = "ball"
layout = "single"
position = [0.0, 0.0, 0.12]

[[bodies]]
name = "can"
shape = "can"
layout = "single"
position = [0.09, 0.0, 0.06]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "wood"
"""

SIZE = (320, 180)


@pytest.fixture(scope="module")
def egl():
    """An offscreen OpenGL context, or the reason there is none: a failure on CI (which
    must have libEGL and Mesa), a skip on a developer's machine without them."""
    from dempipe.preview.gl import create_context

    try:
        create_context().release()
    except preview.PreviewError as exc:
        if os.environ.get("CI"):
            pytest.fail(str(exc))
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def bakes(tmp_path_factory):
    d = tmp_path_factory.mktemp("preview")
    scene = d / "scene.toml"
    scene.write_text(SCENE)
    from dempipe.spheres.cache import SphereCache

    cache = SphereCache(d / "cache")
    return {layout: bake(scene, d / f"{layout}{ext}", device="cpu", layout=layout,
                         cache=cache).path
            for layout, ext in (("instancer", ".usdc"), ("xforms", ".usda"))}


def body_centres_and_colors(path, frame):
    """World centre of mass (B, 3) and displayColor (B, 3) of every body, read with pxr."""
    stage = Usd.Stage.Open(str(path))
    t = Usd.TimeCode(frame)
    inst = stage.GetPrimAtPath("/World/Bodies")
    if inst.IsA(UsdGeom.PointInstancer):
        pi = UsdGeom.PointInstancer(inst)
        xf = np.array(pi.ComputeInstanceTransformsAtTime(t, t))
        protos = pi.GetPrototypesRel().GetTargets()
        colors = [UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(protos[i])).GetPrimvar(
            "displayColor").Get()[0] for i in pi.GetProtoIndicesAttr().Get()]
        return xf[:, 3, :3], np.array(colors)
    cache = UsdGeom.XformCache(t)
    centres, colors = [], []
    for group in inst.GetChildren():
        for body in group.GetChildren():
            centres.append(np.array(cache.GetLocalToWorldTransform(body))[3, :3])
            mesh = [p for p in Usd.PrimRange(body, Usd.TraverseInstanceProxies())
                    if p.IsA(UsdGeom.Mesh)][0]
            colors.append(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor").Get()[0])
    return np.array(centres), np.array(colors)


def nearest_color(pixel, candidates):
    """Index of the candidate linear colour closest in chromaticity to an sRGB-ish pixel.
    Shading scales a colour (sun, sky, shadow) but keeps its chromaticity, up to the
    ambient light's slight tint."""
    lin = (np.asarray(pixel, np.float64) / 255.0) ** 2.2
    chroma = lin / max(lin.sum(), 1e-9)
    cand = np.asarray(candidates, np.float64)
    cand = cand / cand.sum(axis=1, keepdims=True)
    return int(np.argmin(np.linalg.norm(cand - chroma, axis=1)))


def color_at(img, xy):
    x, y = (int(round(v)) for v in xy)
    return np.median(img[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3), axis=0)


GREY = (0.55, 0.55, 0.55)


@pytest.mark.parametrize("layout", ["instancer", "xforms"])
def test_bodies_are_where_the_usd_says(egl, bakes, layout):
    with preview.Preview(bakes[layout], size=SIZE) as pv:
        assert pv.frames == list(range(0, 7))
        for frame in (pv.frames[0], pv.frames[-1]):
            img = pv.image(frame)
            assert img.shape == (SIZE[1], SIZE[0], 3) and img.dtype == np.uint8
            assert img.std() > 10, "blank picture"
            centres, colors = body_centres_and_colors(bakes[layout], frame)
            assert len({tuple(c) for c in colors}) == 3, "the test needs distinct colours"
            candidates = list(colors) + [GREY]
            pix = pv.camera.project(centres)
            assert ((pix > 0) & (pix < SIZE)).all(), "bodies outside the picture"
            for b, xy in enumerate(pix):
                assert nearest_color(color_at(img, xy), candidates) == b, (frame, b, xy)


def test_first_and_last_frames_differ_where_bodies_moved(egl, bakes):
    with preview.Preview(bakes["instancer"], size=SIZE) as pv:
        first, last = pv.image(pv.frames[0]), pv.image(pv.frames[-1])
        c0, colors = body_centres_and_colors(bakes["instancer"], pv.frames[0])
        c1, _ = body_centres_and_colors(bakes["instancer"], pv.frames[-1])
        ball = 1
        assert c0[ball, 2] - c1[ball, 2] > 0.05      # it fell more than its diameter
        p0 = pv.camera.project(c0[ball:ball + 1])[0]
        candidates = list(colors) + [GREY]
        assert nearest_color(color_at(first, p0), candidates) == ball
        assert nearest_color(color_at(last, p0), candidates) != ball
        changed = np.abs(first.astype(int) - last.astype(int)).sum(axis=2) > 30
        assert changed.any()
        x, y = (int(v) for v in p0)
        assert changed[y - 2:y + 3, x - 2:x + 3].all()
        # far from every body the picture stays the same (the camera is fixed)
        assert not changed[:10, :10].any()


def test_both_layouts_give_the_same_picture(egl, bakes):
    """Same bake, two layouts: only the quaternions' precision (half against float)
    differs, so at most a few edge pixels may."""
    images = []
    for layout in ("instancer", "xforms"):
        with preview.Preview(bakes[layout], size=SIZE) as pv:
            images.append(pv.image())
    diff = np.abs(images[0].astype(int) - images[1].astype(int)).max(axis=2)
    assert (diff > 40).mean() < 0.002


def _dempipe(*args, env=None, cwd=None):
    return subprocess.run([sys.executable, "-m", "dempipe_cli.main", *map(str, args)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=600)


def test_cli_still_and_movies(egl, bakes, tmp_path):
    png = tmp_path / "still.png"
    proc = _dempipe("preview", bakes["xforms"], "-o", png, "--frame", 3, "--size", "160x90",
                    "--camera", "top")
    assert proc.returncode == 0, proc.stderr
    from PIL import Image

    with Image.open(png) as im:
        assert im.size == (160, 90)
    mp4 = tmp_path / "movie.mp4"
    proc = _dempipe("preview", bakes["instancer"], "-o", mp4, "--frames", "2:6", "--size",
                    "160x96")
    assert proc.returncode == 0, proc.stderr
    assert "frame 5/5" in proc.stderr
    import av

    with av.open(str(mp4)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (96, 160, 3)
    gif = tmp_path / "movie.gif"
    proc = _dempipe("preview", bakes["instancer"], "-o", gif, "--size", "96x64", "-q")
    assert proc.returncode == 0, proc.stderr
    with Image.open(gif) as im:
        # Pillow merges identical consecutive frames (bodies at rest) into a longer one:
        # the playing time is what must hold: 7 frames of 1/24 s, each stored in 10 ms units
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
        assert abs(sum(durations) - 7 * 1000 / 24) <= 7 * 5 and im.size == (96, 64)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["movie.gif", "movie.mp4", "still.png"]


def test_contact_sheet(egl, bakes, tmp_path):
    out = preview.contact_sheet([bakes["instancer"], bakes["xforms"]], tmp_path / "sheet.png",
                                labels=["instancer", "xforms"], tile=SIZE)
    from PIL import Image

    sheet = np.asarray(Image.open(out).convert("RGB"))
    assert sheet.shape == (SIZE[1], 2 * SIZE[0], 3)
    with preview.Preview(bakes["xforms"], size=SIZE) as pv:
        alone = pv.image()
    tile = sheet[:, SIZE[0]:]
    # the tile is the last frame, but for its frame and label in the top-left corner
    same = np.abs(tile.astype(int) - alone.astype(int)).max(axis=2) <= 2
    assert same[SIZE[1] // 3:-3, 3:-3].mean() > 0.99
    with pytest.raises(preview.PreviewError, match="labels"):
        preview.contact_sheet([bakes["xforms"]], tmp_path / "x.png", labels=["a", "b"])


def test_generic_stage_material_and_time_sampled_xform_ops(egl, tmp_path):
    """Not a dempipe bake: a cube under an Xform with time-sampled translate, coloured by a
    bound UsdPreviewSurface (which wins over its displayColor, as in Hydra), no time range."""
    path = tmp_path / "generic.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    xf = UsdGeom.Xform.Define(stage, "/Root/Mover")
    op = xf.AddTranslateOp()
    op.Set(Gf.Vec3d(-1, 2, 0), 1)
    op.Set(Gf.Vec3d(1, 0.5, 0), 10)
    cube = UsdGeom.Mesh.Define(stage, "/Root/Mover/Cube")
    pts = [(x, y, z) for x in (-0.3, 0.3) for y in (-0.3, 0.3) for z in (-0.3, 0.3)]
    cube.CreatePointsAttr(pts)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    cube.CreateFaceVertexCountsAttr([4] * 6)
    cube.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    cube.CreateDisplayColorAttr([(0.9, 0.1, 0.1)])
    mat = UsdShade.Material.Define(stage, "/Root/Looks/Green")
    shader = UsdShade.Shader.Define(stage, "/Root/Looks/Green/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.1, 0.7, 0.1))
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(cube.GetPrim()).Bind(mat)
    floor = UsdGeom.Mesh.Define(stage, "/Root/Floor")
    floor.CreatePointsAttr([(-3, -0.5, -3), (3, -0.5, -3), (3, -0.5, 3), (-3, -0.5, 3)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateDisplayColorAttr([(0.1, 0.2, 0.9)])
    stage.Save()

    with preview.Preview(path, size=SIZE, camera="front") as pv:
        assert pv.frames == [1, 10]
        candidates = [(0.1, 0.7, 0.1), (0.9, 0.1, 0.1), (0.1, 0.2, 0.9), (0.8, 0.82, 0.85)]
        for frame, centre in ((1, (-1, 2, 0)), (10, (1, 0.5, 0))):
            img = pv.image(frame)
            xy = pv.camera.project([centre])[0]
            assert nearest_color(color_at(img, xy), candidates) == 0
        # the floor (static, drawn, blue) behind and below the cube
        floor_point = pv.camera.project([(0.0, -0.5, -2.5)])[0]
        assert ((floor_point > 0) & (floor_point < SIZE)).all()
        assert nearest_color(color_at(img, floor_point), candidates) == 2


def test_ground_grid_without_colliders(egl, bakes, tmp_path):
    """The bake with its colliders deactivated in an overlay (a sublayer): the ground gets
    a grid under the bodies, with lines on the multiples of its step."""
    from dempipe.preview.gl import ground_grid

    layer = Sdf.Layer.CreateNew(str(tmp_path / "overlay.usda"))
    layer.subLayerPaths.append(str(bakes["instancer"]))
    stage = Usd.Stage.Open(layer)
    stage.OverridePrim("/World/Colliders").SetActive(False)
    layer.Save()
    with preview.Preview(tmp_path / "overlay.usda", size=(640, 360)) as pv:
        assert not pv.has_statics
        img = pv.image()
        height, step, _, _ = ground_grid(*pv.bounds, "Z")
        y = step * (np.floor(pv.bounds[0][1] / step) - 1)    # in front of the bodies
        on_line = pv.camera.project([(0.0, y, height)])[0]
        in_cell = pv.camera.project([(step / 2, y + step / 2, height)])[0]
        assert ((on_line > 2) & (on_line < (638, 358))).all(), on_line
        assert ((in_cell > 2) & (in_cell < (638, 358))).all(), in_cell
        x, y = (int(round(v)) for v in on_line)
        darkest_near_line = img[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3).sum(axis=1).min()
        assert darkest_near_line + 45 < color_at(img, in_cell).sum()


def test_bad_files_one_line_and_nothing_written(bakes, tmp_path):
    garbage = tmp_path / "garbage.usdc"
    garbage.write_bytes(b"not a crate file\x00\x01")
    empty = tmp_path / "empty.usda"
    Usd.Stage.CreateNew(str(empty)).Save()
    no_frames = tmp_path / "no_frames.usda"
    stage = Usd.Stage.CreateNew(str(no_frames))
    UsdGeom.Mesh.Define(stage, "/Tri").CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    stage.SetStartTimeCode(10)
    stage.SetEndTimeCode(5)
    stage.Save()
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out.png"
    out.write_bytes(b"previous")
    cases = [
        ((garbage, "-o", out), "not a USD file"),
        ((empty, "-o", out), "not a dempipe bake"),
        ((no_frames, "-o", out), "no frames"),
        ((scene, "-o", out), "not a USD file"),
        ((tmp_path / "missing.usdc", "-o", out), "no such file"),
        ((bakes["instancer"], "-o", out, "--frame", 99), "--frame 99: outside"),
        ((bakes["instancer"], "-o", tmp_path / "m.mp4", "--frames", "3:40"), "--frames 3:40"),
        ((bakes["instancer"], "-o", tmp_path / "x.jpg"), "unknown extension"),
        ((bakes["instancer"], "-o", out, "--size", "big"), "--size"),
        ((bakes["instancer"], "-o", tmp_path / "m.mp4", "--size", "161x90"), "even"),
    ]
    for args, words in cases:
        proc = _dempipe("preview", *args)
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in proc.stderr, lines
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "empty.usda", "garbage.usdc", "no_frames.usda", "out.png", "scene.toml"]


BLOCK = textwrap.dedent("""
    import sys
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("moderngl", "glcontext", "av", "PIL"):
                raise ModuleNotFoundError(f"No module named {name!r}")
            return None
    sys.meta_path.insert(0, Block())
    from dempipe_cli.main import main
    main(sys.argv[1:])
""")


def test_without_the_extra_the_rest_runs_and_preview_says_how_to_install(bakes, tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-c", BLOCK, *map(str, args)],
                              capture_output=True, text=True, timeout=300)

    proc = run("preview", bakes["instancer"], "-o", tmp_path / "p.png")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: dempipe preview needs the preview extra (moderngl, av, pillow): "
        "pip install 'dempipe[preview]'"]
    assert not (tmp_path / "p.png").exists()
    help_ = run("--help")
    assert help_.returncode == 0 and "preview" in help_.stdout and "bake" in help_.stdout
    check = run("check", Path(__file__).parents[2] / "examples" / "quickstart.toml")
    assert check.returncode == 0, check.stderr


def test_without_egl_one_line_naming_the_system_packages(bakes, tmp_path):
    """A farm node without libEGL/libGL: stand-ins that dlopen cannot load come first on
    LD_LIBRARY_PATH, so context creation really fails."""
    fake = tmp_path / "lib"
    fake.mkdir()
    for name in ("libEGL.so.1", "libEGL.so", "libGL.so.1", "libGL.so"):
        (fake / name).write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    env["LD_LIBRARY_PATH"] = str(fake)
    proc = _dempipe("preview", bakes["instancer"], "-o", tmp_path / "p.png", env=env)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot create an offscreen OpenGL context" in lines[0]
    assert "apt-get install libegl1" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "p.png").exists()


def test_the_extra_is_optional():
    """`pip install dempipe` must not pull the renderer or the encoder."""
    try:
        import tomllib
    except ImportError:     # Python 3.10
        import tomli as tomllib
    meta = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())["project"]
    base = " ".join(meta["dependencies"]).lower()
    for name in ("moderngl", "av", "pillow"):
        assert not any(d.lower().startswith(name) for d in meta["dependencies"]), base
        assert any(d.lower().startswith(name) for d in meta["optional-dependencies"]["preview"])
        assert any(d.lower().startswith(name) for d in meta["optional-dependencies"]["test"])
    assert "dempipe.preview" in (Path(__file__).parents[2] / "pyproject.toml").read_text()


def test_simplify_keeps_the_shape_within_a_cell():
    """The level of detail for big piles: fewer triangles, every point within a cell of
    the original surface's bounds, a closed mesh stays a surface around the centre."""
    import trimesh

    from dempipe.preview.reader import Geometry, simplify

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.02)
    g = Geometry("ball", mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32))
    cell = 0.04 / 12
    s = simplify(g, cell)
    assert 0 < len(s.triangles) < len(g.triangles) / 4
    r = np.linalg.norm(s.points[np.unique(s.triangles)], axis=1)
    assert (np.abs(r - 0.02) <= cell * np.sqrt(3)).all()
    assert np.allclose(s.lo, g.lo, atol=cell) and np.allclose(s.hi, g.hi, atol=cell)
    assert simplify(g, 0.0) is g
