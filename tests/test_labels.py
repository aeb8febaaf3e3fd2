"""Label sets and graph classes."""

from __future__ import annotations

import numpy as np

from cadreg.labels import (
    GRAPH_CLASSES, NYU40, SHAPENET_SYNSETS, STRUCTURE_CLASSES, default_label_maps, is_object_class,
    labels_to_class_index, nyu40_label_map, shapenet_label_map, synset_class,
)


def test_nyu40_table_is_complete():
    assert sorted(NYU40) == list(range(41))
    assert (NYU40[1], NYU40[2], NYU40[5], NYU40[7], NYU40[8], NYU40[9], NYU40[22], NYU40[30], NYU40[39]) == (
        "wall", "floor", "chair", "table", "door", "window", "ceiling", "whiteboard", "otherfurniture")
    assert len(set(NYU40.values())) == 41


def test_structure_is_not_an_object():
    for name in ("wall", "floor", "ceiling", "unlabeled"):
        assert name in STRUCTURE_CLASSES and not is_object_class(name) and name not in GRAPH_CLASSES
    assert is_object_class("chair") and not is_object_class(None)
    assert set(GRAPH_CLASSES) == {n for n in NYU40.values() if n not in STRUCTURE_CLASSES}


def test_nyu40_and_shapenet_meet_in_the_same_classes():
    nyu, sn = nyu40_label_map(), shapenet_label_map()
    assert nyu[5] == sn[int("03001627")] == synset_class("03001627") == "chair"
    assert nyu[7] == synset_class("04379243") == "table"
    # the scene0470 bin (a ShapeNet trash bin) stands on NYU40 39
    assert nyu[39] == synset_class("02747177") == "otherfurniture"
    assert all(cls in GRAPH_CLASSES for _, cls in SHAPENET_SYNSETS.values())
    assert synset_class("99999999") == "otherfurniture"
    assert set(default_label_maps()) == {"nyu40", "shapenet"}


def test_labels_to_class_index_many_to_one_and_unknowns():
    classes = list(GRAPH_CLASSES)
    labels = np.array([[0, 1, 2, 5], [7, 39, 22, 41], [8, 9, 30, 65535]], dtype=np.uint16)
    idx = labels_to_class_index(labels, nyu40_label_map(), classes)
    assert idx.shape == labels.shape and idx.dtype == np.int16
    names = [[classes[i] if i >= 0 else None for i in row] for row in idx]
    assert names == [[None, None, None, "chair"], ["table", "otherfurniture", None, None],
                     ["door", "window", "whiteboard", None]]
    both = {5: "chair", 6: "chair", 3001627: "chair"}
    out = labels_to_class_index(np.array([5, 6, 3001627, 4]), both, classes)
    assert out.tolist() == [classes.index("chair")] * 3 + [-1]
    # a class the site does not know maps to none rather than to a wrong index
    assert labels_to_class_index(np.array([5]), {5: "spaceship"}, classes).tolist() == [-1]
    assert labels_to_class_index(np.zeros((0,), np.uint16), nyu40_label_map(), classes).shape == (0,)
