"""``usl-convert-hypersim``: downloaded Hypersim scenes -> multi-view records (docs/design.md §3-4).

Decisions a user of the records should know (details in each module):

* One record scene is one camera trajectory of one Hypersim scene: ``scene_id = "ai_001_001/cam_00"``,
  ``view_id`` = the frame number in the file names (``frame.0042`` -> 42). The paper samples its M
  views "from the corresponding video", and the trajectories of one Hypersim scene often explore
  different rooms, so views of two trajectories mostly share no object. Instance ids are Hypersim's
  scene-global ``semantic_instance`` ids and poses are in the scene's world frame, so a loader that
  wants cross-trajectory views can still group record scenes by the part before the ``/``.
* World frame: Hypersim's asset frame (+z up) scaled to metres by ``meters_per_asset_unit`` of
  ``_detail/metadata_scene.csv``. Camera axes are OpenCV's (Hypersim's camera is OpenGL-like).
* ``K`` is the full 3x3 projection derived from the scene's ``M_cam_from_uv`` (tilt-shift scenes
  included), for the stored resolution; ``depth`` is planar depth (camera z) in metres.
* Categories are NYU40 ids 1..40. By default every category is kept, walls, floors and ceilings
  included, as the paper describes Hypersim (40 categories, instance ids linked across views);
  ``--exclude-categories stuff`` drops wall, floor and ceiling instances.
* An instance's category is the majority NYU40 label over all its pixels in the converted frames of
  its trajectory (ties -> smaller id), so it is the same in every view.
* Official split and exclusions come from ``metadata_images_split_scene_v1.csv``; excluded frames
  are never converted, even when their files are on disk, and are counted in the manifest.
* Per-frame problems (missing or unreadable files, shapes that disagree, no valid geometry, a camera
  orientation that is not a rotation) become recorded skips; problems with a scene's metadata
  (camera CSV row, pose files, ``metadata_scene.csv``) stop the build with a ``UslError``.
"""
