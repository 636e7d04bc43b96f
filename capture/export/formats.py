"""The formats ``gonio export`` writes (a light module: ``gonio --help`` reads it)."""

#: what each --format writes
FORMATS = {
    "maps": "texture maps in the mesh's UV atlas: textures/*.exr (32-bit float) and *.png (16-bit), "
            "mesh.ply with the UVs; diffuse albedo, GGX lobe scale and roughness, tangent-space normal "
            "map (MikkTSpace convention), material labels, confidence (samples, no-highlight flags)",
    "gltf": "model.glb: glTF 2.0 binary, metallic-roughness + KHR_materials_specular per texel, the "
            "normal map and tangents; loads in any glTF viewer",
    "mitsuba": "mitsuba/: Mitsuba 3 scene (object.xml + PLY + EXR textures) and one XML per captured "
               "pose with the calibrated camera and that capture's point light",
    "merl": "brdf.binary: the tabulated isotropic BRDF in MERL's binary format (90 x 90 x 180); "
            "passive reflectometry's table",
}
