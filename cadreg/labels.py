"""Label sets and graph classes.

A *label set* names how a producer numbers its semantic labels (NYU40 for ScanNet frames and meshes, ShapeNet
synsets for CAD models). The semantic graph speaks *graph classes* (plain names such as "chair"). A `LabelMap` is
`{label set name: {label id: graph class}}`, many-to-one allowed: ShapeNet's trash bin (02747177) and NYU40's
otherfurniture (39) both become "otherfurniture", because that is what ScanNet's annotators gave the bin's vertices.

Structure classes (wall, floor, ceiling, unlabeled) are not objects: they map to no graph class (index -1).
Every site stores its label maps, so a frame in any known label set can be turned into graph classes.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

# NYU40 ids as used by ScanNet's `*.labels.ply` and label images (0 = unlabeled).
NYU40: dict[int, str] = {
    0: "unlabeled",
    1: "wall",
    2: "floor",
    3: "cabinet",
    4: "bed",
    5: "chair",
    6: "sofa",
    7: "table",
    8: "door",
    9: "window",
    10: "bookshelf",
    11: "picture",
    12: "counter",
    13: "blinds",
    14: "desk",
    15: "shelves",
    16: "curtain",
    17: "dresser",
    18: "pillow",
    19: "mirror",
    20: "floor mat",
    21: "clothes",
    22: "ceiling",
    23: "books",
    24: "refridgerator",
    25: "television",
    26: "paper",
    27: "towel",
    28: "shower curtain",
    29: "box",
    30: "whiteboard",
    31: "person",
    32: "night stand",
    33: "toilet",
    34: "sink",
    35: "lamp",
    36: "bathtub",
    37: "bag",
    38: "otherstructure",
    39: "otherfurniture",
    40: "otherprop",
}

# Label names that are the building, not things in it: never graph nodes.
STRUCTURE_CLASSES: frozenset[str] = frozenset({"unlabeled", "wall", "floor", "ceiling", "otherstructure"})

# ShapeNet core synsets -> (ShapeNet name, graph class). The graph class follows ScanNet's NYU40 annotation of the
# same objects, so a CAD node and the labelled frame points of that object share a class.
SHAPENET_SYNSETS: dict[str, tuple[str, str]] = {
    "02747177": ("trash bin", "otherfurniture"),
    "02773838": ("bag", "bag"),
    "02801938": ("basket", "otherprop"),
    "02808440": ("bathtub", "bathtub"),
    "02818832": ("bed", "bed"),
    "02828884": ("bench", "otherfurniture"),
    "02871439": ("bookshelf", "bookshelf"),
    "02876657": ("bottle", "otherprop"),
    "02933112": ("cabinet", "cabinet"),
    "02946921": ("can", "otherprop"),
    "03001627": ("chair", "chair"),
    "03207941": ("dishwasher", "otherfurniture"),
    "03211117": ("display", "television"),
    "03325088": ("faucet", "otherprop"),
    "03337140": ("file cabinet", "cabinet"),
    "03636649": ("lamp", "lamp"),
    "03642806": ("laptop", "otherprop"),
    "03761084": ("microwave", "otherprop"),
    "03928116": ("piano", "otherfurniture"),
    "03938244": ("pillow", "pillow"),
    "03991062": ("pot", "otherprop"),
    "04004475": ("printer", "otherprop"),
    "04256520": ("sofa", "sofa"),
    "04330267": ("stove", "otherfurniture"),
    "04379243": ("table", "table"),
    "04401088": ("telephone", "otherprop"),
    "04554684": ("washer", "otherfurniture"),
}

# Graph classes: every NYU40 name that is an object, in NYU40 order (stable indices across sites).
GRAPH_CLASSES: tuple[str, ...] = tuple(name for _, name in sorted(NYU40.items()) if name not in STRUCTURE_CLASSES)

LabelMap = dict[str, dict[int, str]]


def is_object_class(name: str | None) -> bool:
    """True for a graph class that can be a node (not structure, not None)."""
    return name is not None and name not in STRUCTURE_CLASSES


def nyu40_label_map() -> dict[int, str]:
    """NYU40 id -> graph class for the object ids (structure ids are left out: they map to no class)."""
    return {i: name for i, name in NYU40.items() if is_object_class(name)}


def shapenet_label_map() -> dict[int, str]:
    """ShapeNet synset (as int, e.g. 3001627) -> graph class."""
    return {int(s): cls for s, (_, cls) in SHAPENET_SYNSETS.items()}


def label_set_name(name: str) -> str:
    """A label set's name as sites and frames key it: lower case (DESIGN §2 writes "NYU40", the bundles "nyu40";
    a client's "NYU40" or "ScanNet20" names the same set)."""
    return str(name).lower()


def default_label_maps() -> LabelMap:
    """The label maps every site carries unless told otherwise."""
    return {"nyu40": nyu40_label_map(), "shapenet": shapenet_label_map()}


def synset_class(synset: str) -> str:
    """Graph class of a ShapeNet synset id ("03001627" -> "chair"); unknown synsets become "otherfurniture"
    (a CAD model is furniture-sized by construction; an object node beats no node)."""
    entry = SHAPENET_SYNSETS.get(str(synset).zfill(8))
    return entry[1] if entry else "otherfurniture"


def labels_to_class_index(
    labels: np.ndarray, label_map: Mapping[int, str], classes: list[str] | tuple[str, ...]
) -> np.ndarray:
    """Map label ids to class indices.

    labels : (...) integer array of ids in the label set of `label_map`.
    Returns the same shape, int16 index into `classes`, -1 = none/structure/unknown id.
    """
    labels = np.asarray(labels)
    index = {c: i for i, c in enumerate(classes)}
    pairs = sorted((int(k), index[c]) for k, c in label_map.items() if is_object_class(c) and c in index)
    out = np.full(labels.shape, -1, dtype=np.int16)
    if not pairs or labels.size == 0:
        return out
    # searchsorted, not a dense table: ShapeNet synset ids run into the millions
    keys = np.array([k for k, _ in pairs], dtype=np.int64)
    values = np.array([v for _, v in pairs], dtype=np.int16)
    flat = labels.astype(np.int64).ravel()
    pos = np.clip(np.searchsorted(keys, flat), 0, len(keys) - 1)
    hit = keys[pos] == flat
    out.ravel()[hit] = values[pos[hit]]
    return out
