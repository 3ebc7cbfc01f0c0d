"""Scene-Shapes (paper Sec. 4.1, Appendix B): pairs of chairs, sofas and tables seen from an orbit.

``usl-build-scene-shapes --out DIR`` writes the records of docs/design.md §3 (frames with RGB, depth
and instance masks; objects with the ground-truth meshes). Modules:

- ``primitives``, ``chairs``, ``sofas``, ``tables``, ``shapes``: procedural furniture (5 chair,
  5 sofa, 6 table families, metric sizes), ``source_id = proc/<category>/<family>/<index>``;
- ``mesh_root``: the user's own meshes (ShapeNet-style folders + a category map) instead;
- ``layout``: object placement and camera orbit; its docstring defines the world frame
  (camera 0's ground frame, +Y up, metres) and the view order;
- ``render`` + ``floor``: pyrender/EGL rendering with random materials, lights and background;
- ``scene``: one scene -> one ``SceneRecord``; ``plan``: model/scene splits and shards; ``cli``.
"""
