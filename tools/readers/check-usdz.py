"""Checks a .usdz with USD itself (PyPI's usd-core): the package's layout
(every file stored, its data on 64 bytes, the stage first), every
validator USD registers (UsdValidation: the usdz package rules, file types,
material bindings, shader inputs, ...), and that the mesh's `st` is bound
to a UsdUVTexture through the material. Prints a JSON report; exits 1 on
any problem. With --arrays, the report also holds the first mesh's arrays
as USD reads them (points, faceVertexCounts, faceVertexIndices, st and its
interpolation, extent) and the texture's asset path. Usage: python3
check-usdz.py FILE.usdz [--arrays] (tests/formats.rs)."""
import json
import sys

from pxr import Sdf, Usd, UsdGeom, UsdShade, UsdValidation

path = sys.argv[1]
problems = []
z = Sdf.ZipFile.Open(path)
names = list(z.GetFileNames())
for n in names:
    info = z.GetFileInfo(n)
    if info.dataOffset % 64:
        problems.append(f"{n}: data at {info.dataOffset}, not on 64 bytes")
    if info.compressionMethod != 0:
        problems.append(f"{n}: compressed (method {info.compressionMethod})")
if not names or not names[0].endswith((".usda", ".usdc", ".usd")):
    problems.append(f"the first file is not a USD layer: {names}")
stage = Usd.Stage.Open(path)
registry = UsdValidation.ValidationRegistry()
context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
for e in context.Validate(stage):
    problems.append(f"{e.GetName()}: {e.GetMessage()}")
meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
textured = 0
triangles = 0
for prim in meshes:
    mesh = UsdGeom.Mesh(prim)
    triangles += len(mesh.GetFaceVertexCountsAttr().Get() or [])
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if not st or not st.HasValue():
        problems.append(f"{prim.GetPath()} has no st")
        continue
    values = st.Get()
    if any(not (0 <= v <= 1) for uv in values for v in uv):
        problems.append(f"{prim.GetPath()}: st outside [0, 1]")
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not material:
        problems.append(f"{prim.GetPath()} has no material")
        continue
    for shader in (p for p in Usd.PrimRange(material.GetPrim()) if p.IsA(UsdShade.Shader)):
        if UsdShade.Shader(shader).GetIdAttr().Get() == "UsdUVTexture":
            reader = UsdShade.Shader(shader).GetInput("st").GetConnectedSources()[0]
            if reader and UsdShade.Shader(reader[0].source.GetPrim()).GetInput("varname").Get() == "st":
                textured += 1
report = {
    "files": names,
    "meshes": len(meshes),
    "triangles": triangles,
    "textured": textured,
    "up": UsdGeom.GetStageUpAxis(stage),
    "metersPerUnit": UsdGeom.GetStageMetersPerUnit(stage),
    "problems": problems,
}
if "--arrays" in sys.argv[2:] and meshes:
    mesh = UsdGeom.Mesh(meshes[0])
    st = UsdGeom.PrimvarsAPI(meshes[0]).GetPrimvar("st")
    textures = [p for p in stage.Traverse() if p.IsA(UsdShade.Shader) and UsdShade.Shader(p).GetIdAttr().Get() == "UsdUVTexture"]
    report["arrays"] = {
        "points": [list(p) for p in mesh.GetPointsAttr().Get()],
        "faceVertexCounts": list(mesh.GetFaceVertexCountsAttr().Get()),
        "faceVertexIndices": list(mesh.GetFaceVertexIndicesAttr().Get()),
        "st": [list(v) for v in st.Get()],
        "interpolation": st.GetInterpolation(),
        "extent": [list(p) for p in mesh.GetExtentAttr().Get()],
        "texture": [UsdShade.Shader(t).GetInput("file").Get().path for t in textures],
    }
print(json.dumps(report))
sys.exit(1 if problems else 0)
