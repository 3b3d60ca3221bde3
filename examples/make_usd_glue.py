"""Writes examples/usd_glue.usda: a UsdPhysics shot whose column breaks where it lands.

    python examples/make_usd_glue.py          # then:
    dempipe bake examples/usd_glue.usda -o usd_glue_baked.usda

Y-up, centimetres, as a DCC exports it: a floor and a stone column (a Cube scaled to
30 × 100 × 30 cm) tipped 15 degrees, so that it falls over. dempipe's own attributes
(docs/usd-input.md, "Fracture and glue") cut the column into 12 pieces, more of them
near its top where it lands, and glue them; the stone material's glue strength is
what the landing's bonds break past. The baked overlay deactivates /World/Column and
writes its pieces beside it, /World/Column_pieces/piece_00 ...
"""

from pathlib import Path

from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade

OUT = Path(__file__).with_name("usd_glue.usda")


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

    stone = UsdShade.Material.Define(stage, "/World/Looks/Stone")
    api = UsdPhysics.MaterialAPI.Apply(stone.GetPrim())
    api.CreateRestitutionAttr(0.1)
    api.CreateDynamicFrictionAttr(0.6)
    api.CreateStaticFrictionAttr(0.6)
    api.CreateDensityAttr(0.0024)            # kg / cm³ (kilogramsPerUnit 1, cm): 2400 kg/m³
    # the glue: SI whatever the stage's units; a bonded sphere pair carries σ d²
    stone.GetPrim().CreateAttribute("dempipe:glueStrength", Sdf.ValueTypeNames.Double).Set(2.0e5)

    floor = UsdGeom.Cube.Define(stage, "/World/Floor")
    floor.AddTranslateOp().Set(Gf.Vec3d(0, -5, 0))
    floor.AddScaleOp().Set(Gf.Vec3f(500, 5, 500))            # 10 m × 10 cm × 10 m
    UsdPhysics.CollisionAPI.Apply(floor.GetPrim())

    column = UsdGeom.Cube.Define(stage, "/World/Column")
    column.CreateDisplayColorAttr([Gf.Vec3f(0.62, 0.6, 0.55)])
    column.AddTranslateOp().Set(Gf.Vec3d(0, 60, 0))
    column.AddRotateZOp().Set(15.0)                            # tipped: it falls over
    column.AddScaleOp().Set(Gf.Vec3f(15, 50, 15))              # a unit-2 cube: 30 × 100 × 30 cm
    prim = column.GetPrim()
    UsdPhysics.CollisionAPI.Apply(prim)
    UsdPhysics.RigidBodyAPI.Apply(prim)
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(
        stone, UsdShade.Tokens.weakerThanDescendants, "physics")
    attr = prim.CreateAttribute
    T = Sdf.ValueTypeNames
    attr("dempipe:fracture:pieces", T.Int).Set(12)
    attr("dempipe:fracture:seed", T.Int).Set(3)
    # in the column's local space (the unit cube's): near its top end
    attr("dempipe:fracture:impact", T.Point3d).Set(Gf.Vec3d(0, 0.8, 0))
    attr("dempipe:fracture:impactShare", T.Double).Set(0.5)
    attr("dempipe:glue", T.Bool).Set(True)
    stage.GetRootLayer().Save()
    return path


if __name__ == "__main__":
    print(f"wrote {main()}")
