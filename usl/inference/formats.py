"""The output formats ``usl-predict`` writes: torch-free, so its ``--help`` lists them without loading torch."""

FORMATS = ("glb", "obj", "ply", "html")
