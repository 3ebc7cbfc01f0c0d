"""Your own captures -> usl records: posed frames (transforms.json, COLMAP, or SfM) with 2D instance masks
tracked into objects by the ScanNet pipeline's tracker.

Entry point: ``usl-convert-captures`` (``pipelines.captures.cli:main``). Formats, options and costs:
pipelines/captures/README.md and docs/captures.md.
"""
