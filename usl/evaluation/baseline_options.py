"""The baselines' option values, importable without torch (``usl-eval --help`` lists them)."""

DEFAULT_SPHERE_LEVEL = 3  # ico-sphere subdivisions of the sphere baselines
TRUE_DEPTH_SOURCES = ("auto", "centre", "nearest")  # where "w/ true depth" rows read an object's depth
