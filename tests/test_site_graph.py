"""Objects (clustering, boxes) and the semantic graph (paper eq. 3–4)."""

from __future__ import annotations

import itertools

import numpy as np

from cadreg.site.graph import ObjectNode, SemanticGraph, build_graph
from cadreg.site.objects import affine_box, classwise_clusters, euclidean_clusters, points_in_box, upright_box


def _node(i: int, c, cls="chair", source="cluster") -> ObjectNode:
    c = np.asarray(c, float)
    return ObjectNode(id=f"n{i:02d}", cls=cls, centroid=c, box_center=c + 0.01, box_extent=np.array([0.5, 0.4, 0.9]),
                      box_R=np.eye(3), source=source, cad_id=None if source == "cluster" else "a/b", points=100 + i)


def test_edges_join_exactly_the_pairs_within_delta_with_length_and_direction():
    rng = np.random.default_rng(3)
    nodes = [_node(i, rng.uniform(0, 4, 3)) for i in range(25)]
    g = build_graph(nodes, edge_max_m=1.5)
    c = g.centroids()
    assert c.shape == (25, 3)
    for a, b in itertools.combinations(range(25), 2):
        d = np.linalg.norm(c[a] - c[b])
        has = g.graph.has_edge(nodes[a].id, nodes[b].id)
        assert has == (d <= 1.5), (a, b, d)
        if has:
            e = g.graph.edges[nodes[a].id, nodes[b].id]
            assert abs(e["length_m"] - d) < 1e-12
            # direction goes from the smaller id (a) to the larger (b), unit length
            np.testing.assert_allclose(e["direction"], (c[b] - c[a]) / d, atol=1e-12)
    assert g.node("n07") is nodes[7]


def test_graph_dict_round_trip_is_exact():
    rng = np.random.default_rng(4)
    nodes = [_node(i, rng.uniform(0, 3, 3), source="cad" if i % 2 else "cluster") for i in range(9)]
    g = build_graph(nodes, 1.5)
    g2 = SemanticGraph.from_dict(g.to_dict())
    assert g2.to_dict() == g.to_dict()
    assert [n.to_dict() for n in g2.nodes] == [n.to_dict() for n in nodes]
    for a, b, d in g.graph.edges(data=True):
        d2 = g2.graph.edges[a, b]
        assert d2["length_m"] == d["length_m"]
        np.testing.assert_array_equal(d2["direction"], d["direction"])  # both from the smaller id
    assert build_graph([], 1.5).graph.number_of_nodes() == 0


def test_euclidean_clusters_split_by_gap_and_drop_small():
    rng = np.random.default_rng(0)
    line_a = np.stack([np.arange(0, 1, 0.02), np.zeros(50), np.zeros(50)], axis=1)
    line_b = line_a + [1.2, 0, 0]          # 0.22 m gap: separate at 5 cm tolerance
    speck = rng.normal(scale=0.005, size=(5, 3)) + [5, 5, 5]
    pts = np.vstack([line_a, line_b, speck])
    groups = euclidean_clusters(pts, 0.05, min_points=10)
    assert sorted(map(len, groups)) == [50, 50]
    assert {tuple(sorted(g)) for g in groups} == {tuple(range(50)), tuple(range(50, 100))}
    assert len(euclidean_clusters(pts, 0.5, 10)) == 1 + 0  # the lines join, the speck stays too small


def test_classwise_clusters_keep_touching_objects_of_different_classes_apart():
    a = np.stack([np.arange(0, 1, 0.02), np.zeros(50), np.zeros(50)], axis=1)
    b = a + [1.0, 0, 0]  # continues the line: one cluster without classes, two with
    pts = np.vstack([a, b])
    cls = np.array([3] * 50 + [7] * 50)
    out = classwise_clusters(pts, cls, 0.05, 10)
    assert [(c.class_index, len(c.indices)) for c in out] == [(3, 50), (7, 50)]
    assert len(euclidean_clusters(pts, 0.05, 10)) == 1
    none = classwise_clusters(pts, np.full(100, -1), 0.05, 10)
    assert none == []


def test_upright_box_of_a_rotated_rectangle():
    rng = np.random.default_rng(1)
    local = rng.uniform(-0.5, 0.5, (4000, 3)) * [2.0, 0.6, 1.0]
    yaw = np.radians(35)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    pts = local @ R.T + [3, 2, 0.5]
    center, extent, Rb = upright_box(pts)
    np.testing.assert_allclose(center, [3, 2, 0.5], atol=0.02)
    np.testing.assert_allclose(extent, [2.0, 0.6, 1.0], atol=0.03)
    assert abs(abs(Rb[:, 0] @ R[:, 0]) - 1) < 1e-3 and np.allclose(Rb[:, 2], [0, 0, 1])
    assert points_in_box(pts, center, extent, Rb, 1e-9).all()


def test_affine_box_and_points_in_box():
    A = np.diag([0.5, 2.0, 1.0, 1.0])
    A[:3, 3] = [1, 1, 1]
    center, extent, R = affine_box(A, np.array([-1.0, -1, -1]), np.array([1.0, 1, 1]))
    np.testing.assert_allclose(center, [1, 1, 1])
    np.testing.assert_allclose(extent, [1, 4, 2])
    np.testing.assert_allclose(R, np.eye(3))
    pts = np.array([[1.49, 1, 1], [1.51, 1, 1], [1, 2.99, 1], [1, 1, 2.04]])
    assert points_in_box(pts, center, extent, R).tolist() == [True, False, True, False]
    assert points_in_box(pts, center, extent, R, margin_m=0.05).tolist() == [True, True, True, True]


def test_merge_stacked_joins_seat_and_base_but_not_neighbours():
    from cadreg.site.objects import Cluster, merge_stacked

    g = np.linspace(-0.2, 0.2, 9)
    gx, gy = np.meshgrid(g, g)
    disc = np.stack([gx.ravel(), gy.ravel()], axis=1)
    seat = np.hstack([disc, np.full((len(disc), 1), 0.5)])
    base = np.hstack([disc * 0.8, np.full((len(disc), 1), 0.05)])
    other_chair = seat + [1.0, 0, 0]
    table_part = base + [0, 0, 0.3]  # same place, another class: stays apart
    pts = np.vstack([seat, base, other_chair, table_part])
    n = len(disc)
    clusters = [Cluster(2, np.arange(0, n)), Cluster(2, np.arange(n, 2 * n)), Cluster(2, np.arange(2 * n, 3 * n)),
                Cluster(4, np.arange(3 * n, 4 * n))]
    merged = merge_stacked(pts, clusters, 0.5)
    assert [(c.class_index, len(c.indices)) for c in merged] == [(2, 2 * n), (2, n), (4, n)]
    np.testing.assert_array_equal(merged[0].indices, np.arange(2 * n))
    assert len(merge_stacked(pts, clusters, 1.0)) == 3  # the base lies fully under the seat
    # the same chair a storey up is another chair
    upstairs = np.vstack([seat, seat + [0, 0, 3.0]])
    assert len(merge_stacked(upstairs, [Cluster(2, np.arange(n)), Cluster(2, np.arange(n, 2 * n))], 0.5)) == 2


def test_dense_clouds_cluster_on_voxels_with_the_same_answer():
    from cadreg.site import objects

    rng = np.random.default_rng(5)
    # two 1 cm-dense slabs 10 cm apart (separate at 5 cm), 2 × 40,000 points: above the direct-clustering limit
    a = rng.uniform([0, 0, 0], [1.0, 1.0, 0.04], (40000, 3))
    b = a + [0, 0, 0.14]
    pts = np.vstack([a, b])
    assert len(pts) > objects._DIRECT_CLUSTERING_MAX_POINTS
    groups = euclidean_clusters(pts, 0.05, 100)
    assert sorted(map(len, groups)) == [40000, 40000]
    assert {tuple(np.unique(g // 40000)) for g in groups} == {(0,), (1,)}
