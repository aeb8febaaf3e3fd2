"""Object nodes and the semantic graph of a site (paper §2.3.2, eq. 3–4).

Nodes are object instances (CAD-aligned or clustered from labels); an edge joins two nodes whose centroids are at
most δ apart and carries its length (metres) and the unit direction from the first node to the second (map frame;
for the edge (a, b) stored in networkx, `direction` points from the node with the smaller id to the larger one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import networkx as nx
import numpy as np


@dataclass
class ObjectNode:
    """One object instance of the map.

    centroid : (3,) float64, map frame, metres: centre of the axis-aligned box of the object's points (for CAD
        nodes, of the transformed CAD vertices, as the paper's "centroid of the bounding box").
    box_center, box_extent : (3,) float64 centre and full side lengths of the oriented box, metres, map frame.
    box_R : (3, 3) float64 rotation whose columns are the box axes in the map frame.
    source : "cad" (from a Scan2CAD alignment) or "cluster" (from class-wise clustering of labelled map points).
    cad_id : "<synset>/<model id>" for CAD nodes, else None.
    points : number of map points of this instance.
    """

    id: str
    cls: str
    centroid: np.ndarray
    box_center: np.ndarray
    box_extent: np.ndarray
    box_R: np.ndarray
    source: str
    cad_id: str | None
    points: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "class": self.cls,
            "centroid": [float(x) for x in self.centroid],
            "box_center": [float(x) for x in self.box_center],
            "box_extent": [float(x) for x in self.box_extent],
            "box_R": [[float(x) for x in row] for row in self.box_R],
            "source": self.source,
            "cad_id": self.cad_id,
            "points": int(self.points),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ObjectNode":
        return cls(
            id=str(d["id"]),
            cls=str(d["class"]),
            centroid=np.asarray(d["centroid"], dtype=np.float64).reshape(3),
            box_center=np.asarray(d["box_center"], dtype=np.float64).reshape(3),
            box_extent=np.asarray(d["box_extent"], dtype=np.float64).reshape(3),
            box_R=np.asarray(d["box_R"], dtype=np.float64).reshape(3, 3),
            source=str(d["source"]),
            cad_id=d.get("cad_id"),
            points=int(d["points"]),
        )


class SemanticGraph:
    """Nodes (in a fixed order) and a networkx.Graph keyed by node id with edge attributes `length_m` (float) and
    `direction` ((3,) float64 unit vector, map frame, from the smaller node id towards the larger)."""

    def __init__(self, nodes: list[ObjectNode], graph: nx.Graph) -> None:
        self.nodes = list(nodes)
        self.graph = graph
        self._by_id = {n.id: n for n in self.nodes}

    def node(self, id: str) -> ObjectNode:
        return self._by_id[id]

    def centroids(self) -> np.ndarray:
        """(n, 3) float64 node centroids in `nodes` order, map frame."""
        return np.array([n.centroid for n in self.nodes], dtype=np.float64).reshape(-1, 3)

    def classes(self) -> list[str]:
        return [n.cls for n in self.nodes]

    def to_dict(self) -> dict[str, Any]:
        edges = [
            {"a": a, "b": b, "length_m": float(d["length_m"]), "direction": [float(x) for x in d["direction"]]}
            for a, b, d in sorted(self.graph.edges(data=True), key=lambda e: tuple(sorted(e[:2])))
        ]
        for e in edges:
            if e["a"] > e["b"]:
                e["a"], e["b"] = e["b"], e["a"]
                e["direction"] = [-x for x in e["direction"]]
        return {"nodes": [n.to_dict() for n in self.nodes], "edges": edges}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SemanticGraph":
        nodes = [ObjectNode.from_dict(n) for n in d["nodes"]]
        g = nx.Graph()
        g.add_nodes_from(n.id for n in nodes)
        for e in d["edges"]:
            g.add_edge(e["a"], e["b"], length_m=float(e["length_m"]),
                       direction=np.asarray(e["direction"], dtype=np.float64))
        return cls(nodes, g)


def build_graph(nodes: list[ObjectNode], edge_max_m: float) -> SemanticGraph:
    """Join every pair of nodes whose centroids are ≤ edge_max_m (δ) apart (paper eq. 3–4)."""
    from scipy.spatial import cKDTree

    g = nx.Graph()
    for n in nodes:
        g.add_node(n.id, cls=n.cls)
    if len(nodes) >= 2:
        c = np.array([n.centroid for n in nodes], dtype=np.float64)
        for i, j in sorted(cKDTree(c).query_pairs(edge_max_m)):
            a, b = (i, j) if nodes[i].id < nodes[j].id else (j, i)
            d = c[b] - c[a]
            length = float(np.linalg.norm(d))
            direction = d / length if length > 0 else np.zeros(3)
            g.add_edge(nodes[a].id, nodes[b].id, length_m=length, direction=direction)
    return SemanticGraph(nodes, g)
