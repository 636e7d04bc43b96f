"""``gonio export``: a method's recovered appearance -> files other software reads.

``appearance`` what ``gonio process`` stores for export (per texel: position, normals, confidence,
the exported BRDF; the held-out samples and the capture geometry); ``ggx`` the exported BRDF and
its per-material/per-texel fit; ``atlas`` the UV atlas, tangents and baking; ``images`` EXR and
16-bit PNG; ``gltf`` the .glb; ``mitsuba`` the Mitsuba 3 scenes; ``check`` Mitsuba's render read
at the held-out samples; ``session`` the command's work (``export_session``); ``formats`` the
``--format`` names.
"""
