"""The rows and picture selections ``usl-eval`` offers: torch-free, so its ``--help`` can list them and the
evaluation code can check against the same names without importing its command line (the rows'
builders: ``usl.evaluation.rows``)."""

ROWS = (
    "random",
    "fixed",
    "model",
    "detections",
    "layout_only",
    "sphere_true_depth",
    "model_true_depth",
    "sphere_true_layout",
    "model_true_layout",
)
PICTURE_SELECTIONS = ("spread", "extremes")  # see usl.evaluation.gallery
