"""COCO's category ids as the COCO-trained segmenters number their classes (no torch: pipelines import it)."""

# COCO's 80 thing categories have ids 1..90 with these gaps; detectron2's contiguous class k is the k-th.
COCO_ID_GAPS = frozenset({12, 26, 29, 30, 45, 66, 68, 69, 71, 83})
COCO_CATEGORY_IDS = tuple(i for i in range(1, 91) if i not in COCO_ID_GAPS)
# torchvision's COCO models keep a slot per id 1..90 (the gaps never fire): class k is id k + 1.
TORCHVISION_COCO_IDS = tuple(range(1, 91))
