"""Everything pxr writes: the animation in two layouts, overlays over a shot, UsdPhysics stages."""
