"""Every value a scene or a stage gives, mutated: each is read or refused at the door.

Each numeric, string and array value of a rich TOML scene (materials, shapes, a grid,
a single body, an emitter, a kinematic body, a plane) and each UsdPhysics attribute of a
small stage is replaced in turn by a wrong type, a sign, NaN, infinity, 0, 1e300, 1e-300
or a huge integer. What `dempipe check` runs (load, build the Model, analyze: no kernel
compiled) either passes or raises a DempipeError of one line; never another exception,
never a numpy overflow warning. A handful go through the real command.
"""

import math
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from dempipe.errors import DempipeError
from dempipe.pipeline.check import analyze_scene
from dempipe.spheres.cache import SphereCache

SCENE = """
[output]
fps = 24
duration = 0.5
start_frame = 1

[simulation]
resolution = 2
stiffness_target_overlap = 0.1
gravity = [0.0, 0.0, -9.81]
seed = 1

[materials.rubber]
density = 1000.0
restitution = 0.4
friction = 0.6

[materials.heavy]
density = 3000.0
restitution = 0.3
friction = 0.5

[shapes.ball]
builtin = "sphere"
diameter = 0.1

[shapes.box]
builtin = "box"
size = [0.08, 0.06, 0.05]

[[bodies]]
name = "balls"
shape = "ball"
material = "rubber"
layout = "grid"
origin = [-0.2, -0.2, 0.1]
dims = [2, 2, 1]
spacing = 0.14
velocity = [0.3, 0.1, 0.0]
angular_velocity = [0.0, 0.0, 1.0]

[[bodies]]
name = "boxes"
shape = "box"
material = "heavy"
position = [0.3, 0.0, 0.1]
rotation = [1.0, 0.0, 0.0, 0.0]

[[bodies]]
name = "rain"
shape = "ball"
material = "rubber"
layout = "emit"
region_min = [-0.3, -0.3, 0.5]
region_max = [0.3, 0.3, 0.6]
rate = 10.0
count = 4
start_time = 0.1

[[bodies]]
name = "paddle"
shape = "box"
material = "heavy"
position = [0.0, 0.4, 0.1]
kinematic = true
[bodies.motion]
angular_velocity = [0.0, 0.0, 2.0]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rubber"
"""

VALUES = ["0", "-1", "1e300", "-1e300", "1e-300", "-1e-300", "nan", "inf", "-inf", '"x"',
          "true", "[1, 2]", "{}", "1e9", "2147483648000", "-2147483648000"]
ELEMENTS = ["nan", "inf", "1e300", "-1e300", "1e-300", "0", '"x"']


def mutations(text: str):
    """(description, scene text) for each value replaced by each of VALUES, and each
    array element by each of ELEMENTS."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"^(\s*[A-Za-z_]+\s*=\s*)(.*)$", line)
        if not m:
            continue
        lhs, rhs = m.groups()
        variants = list(VALUES)
        if rhs.startswith("["):
            elems = [e.strip() for e in rhs.strip("[]").split(",")]
            for j in range(len(elems)):
                for v in ELEMENTS:
                    variants.append("[" + ", ".join(elems[:j] + [v] + elems[j + 1:]) + "]")
        for v in variants:
            yield f"{line.strip()} -> {v}", "\n".join(lines[:i] + [lhs + v] + lines[i + 1:])


def _check(path: Path, cache) -> str | None:
    """None when ``path`` is read or refused as it should be, else what went wrong."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            analyze_scene(path, cache=cache)
        except DempipeError as exc:
            if "\n" in str(exc) or not str(exc).strip():
                return f"not one line: {exc!r}"
        except Exception as exc:        # noqa: BLE001  (what the test is looking for)
            return f"{type(exc).__name__}: {exc}"
    noise = [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)]
    return f"numpy warning: {noise[0]}" if noise else None


def test_every_scene_value_mutated_is_read_or_one_line(tmp_path):
    cache = SphereCache(tmp_path / "cache")
    base = tmp_path / "base.toml"
    base.write_text(SCENE)
    assert _check(base, cache) is None
    wrong, n = {}, 0
    for what, text in mutations(SCENE):
        path = tmp_path / "m.toml"
        path.write_text(text)
        n += 1
        bad = _check(path, cache)
        if bad:
            wrong[what] = bad
    assert n > 800
    assert wrong == {}


def _stage(path, attr=None, value=None):
    from pxr import Gf, Usd, UsdGeom, UsdPhysics

    st = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(st, "Z")
    st.SetStartTimeCode(0)
    st.SetEndTimeCode(6)
    st.SetTimeCodesPerSecond(24)
    UsdGeom.Xform.Define(st, "/World")
    UsdPhysics.Scene.Define(st, "/World/physicsScene")
    g = UsdGeom.Cube.Define(st, "/World/Ground")
    g.CreateSizeAttr(1.0)
    g.AddTranslateOp().Set(Gf.Vec3d(0, 0, -0.05))
    g.AddScaleOp().Set(Gf.Vec3f(20, 20, 0.1))
    UsdPhysics.CollisionAPI.Apply(g.GetPrim())
    b = UsdGeom.Cube.Define(st, "/World/Box")
    b.CreateSizeAttr(0.1)
    b.AddTranslateOp().Set(Gf.Vec3d(0, 0, 0.2))
    UsdPhysics.CollisionAPI.Apply(b.GetPrim())
    rb = UsdPhysics.RigidBodyAPI.Apply(b.GetPrim())
    rb.CreateVelocityAttr(Gf.Vec3f(0.1, 0, 0))
    rb.CreateAngularVelocityAttr(Gf.Vec3f(0, 0, 10))
    mass = UsdPhysics.MassAPI.Apply(b.GetPrim())
    mass.CreateMassAttr(1.0)
    mass.CreateCenterOfMassAttr(Gf.Vec3f(0, 0, 0))
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(0.002, 0.002, 0.002))
    from pxr import UsdShade

    mat = UsdShade.Material.Define(st, "/World/Mat")
    api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    api.CreateRestitutionAttr(0.5)
    api.CreateDynamicFrictionAttr(0.5)
    api.CreateDensityAttr(1000.0)
    UsdShade.MaterialBindingAPI.Apply(b.GetPrim()).Bind(
        mat, UsdShade.Tokens.weakerThanDescendants, "physics")
    scene = UsdPhysics.Scene(st.GetPrimAtPath("/World/physicsScene"))
    scene.CreateGravityMagnitudeAttr(9.81)
    scene.CreateGravityDirectionAttr(Gf.Vec3f(0, 0, -1))
    if attr is not None:
        prim_path, name = attr
        if prim_path == "/":
            st.GetRootLayer().pseudoRoot.SetInfo(name, value)
        else:
            a = st.GetPrimAtPath(prim_path).GetAttribute(name)
            t = a.GetTypeName()
            a.Set(_typed(t, value, name))
    st.GetRootLayer().Save()


def _typed(type_name, x, name=""):
    from pxr import Gf

    s = str(type_name)
    if name == "physics:gravityDirection":      # along the up axis: a sideways gravity
        return Gf.Vec3f(0.0, 0.0, x)            # makes the ground a box to voxelize
    if s.startswith("float3") or s.startswith("vector3f") or s.startswith("point3f"):
        return Gf.Vec3f(x, 0.0, 0.0)
    if s.startswith("double3"):
        return Gf.Vec3d(x, 0.0, 0.0)
    return x


USD_ATTRS = [("/World/Box", "size"), ("/World/Box", "physics:mass"),
             ("/World/Box", "physics:velocity"), ("/World/Box", "physics:angularVelocity"),
             ("/World/Box", "physics:centerOfMass"), ("/World/Box", "physics:diagonalInertia"),
             ("/World/Box", "xformOp:translate"), ("/World/Mat", "physics:restitution"),
             ("/World/Mat", "physics:dynamicFriction"), ("/World/Mat", "physics:density"),
             ("/World/physicsScene", "physics:gravityMagnitude"),
             ("/World/physicsScene", "physics:gravityDirection"),
             ("/World/Ground", "size"), ("/", "metersPerUnit"), ("/", "kilogramsPerUnit"),
             ("/", "timeCodesPerSecond"), ("/", "startTimeCode"), ("/", "endTimeCode")]
USD_VALUES = [0.0, -1.0, 1e300, -1e300, 1e-300, math.nan, math.inf, -math.inf]


def test_every_stage_attribute_mutated_is_read_or_one_line(tmp_path):
    pytest.importorskip("pxr")
    cache = SphereCache(tmp_path / "cache")
    base = tmp_path / "base.usda"
    _stage(base)
    assert _check(base, cache) is None
    wrong = {}
    for attr in USD_ATTRS:
        for v in USD_VALUES:
            path = tmp_path / f"m{len(wrong)}.usda"
            path.unlink(missing_ok=True)
            _stage(path, attr, v)
            bad = _check(path, cache)
            if bad:
                wrong[f"{attr} = {v!r}"] = bad
    assert wrong == {}


@pytest.mark.parametrize("what", ["materials.rubber.density -> 1e-300",
                                  "output.start_frame -> 2147483648000",
                                  "shapes.box.size -> [1e300, 0.06, 0.05]",
                                  "simulation.gravity -> nan"])
def test_a_few_through_the_real_command(tmp_path, what):
    line = {"materials.rubber.density": "density = 1000.0",
            "output.start_frame": "start_frame = 1", "shapes.box.size": "size = [0.08, 0.06, 0.05]",
            "simulation.gravity": "gravity = [0.0, 0.0, -9.81]"}[what.split(" ->")[0]]
    lhs = line.split("=")[0]
    text = SCENE.replace(line, lhs + "= " + what.split("-> ")[1], 1)
    (tmp_path / "s.toml").write_text(text)
    r = subprocess.run([sys.executable, "-m", "dempipe_cli.main", "check", "s.toml"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**__import__("os").environ, "DEMPIPE_CACHE_DIR": str(tmp_path / "c")})
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: s.toml: "), r.stderr
    assert what.split(" ->")[0].split(".")[-1] in lines[0], r.stderr
