"""Semantic class ids: the one place they are defined.

Ids are what the simulator writes in the PointCloud2 ``label`` field (uint8), what the segmentation
network predicts, and what plane detection filters on. The paper's five classes (floor, wall, pillar,
desk, chair) plus ceiling and other (clutter, people, cars).
"""
OTHER, FLOOR, WALL, PILLAR, DESK, CHAIR, CEILING = range(7)

NAMES = ("other", "floor", "wall", "pillar", "desk", "chair", "ceiling")
NUM_CLASSES = len(NAMES)
ID = {name: i for i, name in enumerate(NAMES)}

#: Classes whose surfaces do not move: only these reach plane detection.
STATIC = (FLOOR, WALL, PILLAR, CEILING)
#: The paper's Table 2 columns.
PAPER_CLASSES = (FLOOR, WALL, PILLAR, DESK, CHAIR)


def class_id(name: str) -> int:
    """Class id for a name, with a clear error for an unknown name."""
    try:
        return ID[name]
    except KeyError:
        raise ValueError(f"unknown class {name!r}; known: {', '.join(NAMES)}") from None
