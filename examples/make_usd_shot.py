"""Writes examples/usd_shot.usda: a shot as a DCC exports it with UsdPhysics.

    python examples/make_usd_shot.py          # then:
    dempipe bake examples/usd_shot.usda -o usd_shot_baked.usda --resolution 6

Y-up, centimetres (as Maya and Houdini scenes often are): a floor, a rubber ball
thrown sideways, a tumbling crate (a Mesh with a physics material), a dumbbell (an
Xform body whose shapes are its two child cubes) under a turned and scaled rig, and
a PointInstancer of three blocks. The baked overlay animates these prims in place.
"""

from pathlib import Path

from pxr import Gf, Usd, UsdGeom, UsdPhysics, UsdShade

OUT = Path(__file__).with_name("usd_shot.usda")


def physics_material(stage, path, restitution, friction, density):
    mat = UsdShade.Material.Define(stage, path)
    api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    api.CreateRestitutionAttr(restitution)
    api.CreateDynamicFrictionAttr(friction)
    api.CreateStaticFrictionAttr(friction)
    api.CreateDensityAttr(density)           # kg / cm³ (kilogramsPerUnit 1, cm)
    return mat


def bind(prim, mat):
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(
        mat, UsdShade.Tokens.weakerThanDescendants, "physics")


def body(prim, velocity=None, angular=None):
    UsdPhysics.CollisionAPI.Apply(prim)
    rb = UsdPhysics.RigidBodyAPI.Apply(prim)
    if velocity:
        rb.CreateVelocityAttr(Gf.Vec3f(*velocity))       # cm/s
    if angular:
        rb.CreateAngularVelocityAttr(Gf.Vec3f(*angular))  # degrees/s


def crate_mesh(stage, path, h):
    m = UsdGeom.Mesh.Define(stage, path)
    c = [(-h, -h, -h), (h, -h, -h), (h, h, -h), (-h, h, -h),
         (-h, -h, h), (h, -h, h), (h, h, h), (-h, h, h)]
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    m.CreatePointsAttr([Gf.Vec3f(*p) for p in c])
    m.CreateFaceVertexCountsAttr([4] * 6)
    m.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    return m


def main(path=OUT):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.centimeters)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(36)
    stage.SetTimeCodesPerSecond(24)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")      # gravity: -Y, 981 cm/s²

    rubber = physics_material(stage, "/World/Looks/Rubber", 0.8, 0.6, 0.0011)
    wood = physics_material(stage, "/World/Looks/Wood", 0.4, 0.5, 0.0007)

    floor = UsdGeom.Cube.Define(stage, "/World/Floor")
    floor.AddTranslateOp().Set(Gf.Vec3d(0, -5, 0))
    floor.AddScaleOp().Set(Gf.Vec3f(500, 5, 500))            # 10 m × 10 cm × 10 m
    UsdPhysics.CollisionAPI.Apply(floor.GetPrim())
    bind(floor.GetPrim(), wood)

    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(4)
    ball.AddTranslateOp().Set(Gf.Vec3d(-40, 12, 0))
    body(ball.GetPrim(), velocity=(80, 0, 0))
    bind(ball.GetPrim(), rubber)

    crate = crate_mesh(stage, "/World/Crate", 4)
    crate.AddTranslateOp().Set(Gf.Vec3d(20, 14, 0))
    crate.AddRotateXYZOp().Set(Gf.Vec3f(30, 0, 20))
    body(crate.GetPrim(), angular=(0, 0, 90))
    bind(crate.GetPrim(), wood)

    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    rig.AddTranslateOp().Set(Gf.Vec3d(0, 0, 40))
    rig.AddRotateYOp().Set(45)
    rig.AddScaleOp().Set(Gf.Vec3f(1.25, 1.25, 1.25))
    dumbbell = UsdGeom.Xform.Define(stage, "/World/Rig/Dumbbell")
    dumbbell.AddTranslateOp().Set(Gf.Vec3d(0, 8, 0))
    UsdPhysics.RigidBodyAPI.Apply(dumbbell.GetPrim())
    for i, x in enumerate((-5, 5)):
        end = UsdGeom.Cube.Define(stage, f"/World/Rig/Dumbbell/End{i}")
        end.CreateSizeAttr(4)
        end.AddTranslateOp().Set(Gf.Vec3d(x, 0, 0))
        UsdPhysics.CollisionAPI.Apply(end.GetPrim())
    bar = UsdGeom.Cylinder.Define(stage, "/World/Rig/Dumbbell/Bar")
    bar.CreateRadiusAttr(1)
    bar.CreateHeightAttr(8)
    bar.CreateAxisAttr("X")
    UsdPhysics.CollisionAPI.Apply(bar.GetPrim())

    blocks = UsdGeom.PointInstancer.Define(stage, "/World/Blocks")
    proto = UsdGeom.Cube.Define(stage, "/World/Blocks/Prototypes/Block")
    proto.CreateSizeAttr(8)
    body(proto.GetPrim())
    bind(proto.GetPrim(), wood)
    blocks.CreatePrototypesRel().SetTargets([proto.GetPath()])
    blocks.CreateProtoIndicesAttr([0, 0, 0])
    blocks.CreatePositionsAttr([Gf.Vec3f(-30, 4.2, -40), Gf.Vec3f(-30, 12.6, -40),
                                Gf.Vec3f(-29, 21, -40)])
    blocks.CreateOrientationsAttr([Gf.Quath(1, 0, 0, 0)] * 3)
    stage.GetRootLayer().Save()
    return path


if __name__ == "__main__":
    print(f"wrote {main()}")
