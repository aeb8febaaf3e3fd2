"""Per-region search structures of a site: what the refinement, the agreement score and the free-space check of
one pose need, built for the region the pose looks into rather than for the whole building (DESIGN §1).

A pose's region is the one that holds the centre of its region of interest (the frame's centroid placed by the
pose, paper §2.5). The region's structures hold the map points inside its box grown by `RegionConfig.halo_m`
(points of neighbouring regions included): with a halo of γ, the ROI radius, the whole ROI of any pose whose
centre lies in the region is covered, so a view from one room into the next through a doorway or an unscanned
wall is refined against both, as it would be against the whole map.

A one-room site has one region and its structures are built once, up front, as before regions existed. A
building's regions are built on first use and kept in a least-recently-used cache of `RegionConfig.max_cached`
regions, so that a worker's memory is bounded by the cache, not by the building.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..config import LocalizeConfig
from ..pointset import PointSet
from ..site.bundle import REGION_GRID_DTYPE, RegionGrids, Site
from ..site.regions import Region, Storeys
from .fallback import FpfhRansac
from .point_tree import LEAF_SIZE, tree_order
from .points import voxel_indices
from .refine import FITNESS_VOXEL_M, RefineMap
from .score import ViewCheck


@dataclass
class RegionIndex:
    """The refinement map and the free-space check of one region (map frame)."""

    region: Region
    refine_map: RefineMap
    view_check: ViewCheck
    fpfh: FpfhRansac | None = None  # FPFH + RANSAC against this region's map (a building's last resort), on first use


def region_cloud(site: Site, region: Region, which: str) -> PointSet:
    """The points of `region` in the site's cloud `which` ("raw" | "enhanced" | "both", as `Site.cloud`)."""
    enhanced = site.map.take(slice(*region.map_range))
    raw = site.raw.take(slice(*region.raw_range))
    if which == "enhanced" or len(site.raw) == 0:
        return enhanced
    return raw if which == "raw" else PointSet.concat([raw, enhanced])


def halo_cloud(site: Site, regions: list[Region], region: Region, which: str, halo_m: float) -> PointSet:
    """The points of cloud `which` inside `region`'s box grown by halo_m: its own and its neighbours' (a region's
    points are a slice of the site's clouds, so only the regions whose boxes reach the grown box are read)."""
    lo, hi = region.bounds[0] - halo_m, region.bounds[1] + halo_m
    parts, read = [], []
    for r in regions:
        if np.any(r.bounds[1] < lo) or np.any(r.bounds[0] > hi):
            continue
        cloud = region_cloud(site, r, which)
        if r is not region:
            xyz = cloud.points
            cloud = cloud.take(np.all((xyz >= lo) & (xyz <= hi), axis=1))
        parts.append(cloud)
        read.append(r)
    out = PointSet.concat(parts)
    # Copied: a memory-mapped building hands the pages it read back (they would stay resident otherwise, and a
    # worker that has localized in every room would hold the whole building).
    for r in read:
        site.release("map", slice(*r.map_range))
        site.release("raw", slice(*r.raw_range))
    return out


def halo_grid(site: Site, regions: list[Region], region: Region, which: str, halo_m: float,
              voxel_m: float = FITNESS_VOXEL_M) -> PointSet:
    """`region`'s `halo_cloud` of cloud `which`, one point per voxel_m voxel: a building's region map."""
    halo = halo_cloud(site, regions, region, which, halo_m)
    return halo.take(voxel_indices(halo.points.astype(np.float64), voxel_m))


def region_grids(site: Site, regions: list[Region], *, cloud: str, halo_m: float,
                 voxel_m: float = FITNESS_VOXEL_M) -> RegionGrids:
    """Each region's `halo_cloud` of cloud `cloud`, one point per voxel_m voxel, in the order of its KD-tree: what
    `site compose` stores (regions.npy) so that a building's region maps, trees included, are made from a read
    (`build_index`)."""
    parts = []
    for region in regions:
        grid = halo_grid(site, regions, region, cloud, halo_m, voxel_m)
        rows = np.zeros(len(grid), dtype=REGION_GRID_DTYPE)
        rows["xyz"], rows["rgb"], rows["cls"] = grid.points, grid.colors, grid.class_index
        parts.append(rows[tree_order(rows["xyz"], LEAF_SIZE)])
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return RegionGrids(np.concatenate(parts) if parts else np.zeros(0, REGION_GRID_DTYPE), offsets, cloud,
                       float(halo_m), float(voxel_m), LEAF_SIZE)


def build_index(site: Site, regions: list[Region], region: Region, config: LocalizeConfig) -> RegionIndex:
    """The structures of one region: a one-room site's of its whole cloud; a building's of its region grid (its box
    and halo, one point per fitness voxel), read as the bundle stores it, else made from the clouds."""
    rc = config.refine
    stored = site.region_grids
    building = len(regions) > 1
    tree_ordered = False
    if building and stored is not None and stored.matches(cloud=rc.map_points, halo_m=config.regions.halo_m,
                                                          voxel_m=FITNESS_VOXEL_M):
        # The region's grid as the bundle stores it: one read, no gather over its neighbours, no gridding (40 of
        # the 65 ms a 100-room building's region map took), and in tree order, no KD-tree to build (15-20 ms).
        k = next(i for i, r in enumerate(regions) if r.id == region.id)
        rows = stored.rows(k)
        # The colours stay a view of the stored rows, read where needed (`RefineMap.rgb_at`: a few hundred rows a
        # refinement; a memory-mapped page handed back below is read again from the file when one is touched).
        xyz, rgb, cls = rows["xyz"].astype(np.float64), rows["rgb"], rows["cls"].astype(np.int64)
        stored.release(k)
        tree_ordered = stored.tree_leaf == LEAF_SIZE
    else:
        cloud = (halo_grid(site, regions, region, rc.map_points, config.regions.halo_m) if building
                 else region_cloud(site, region, rc.map_points))
        xyz, rgb, cls = cloud.points.astype(np.float64), cloud.rgb01(), cloud.class_index
    # A scan's normals face the side it was scanned from: a one-room map keeps them (`RefineMap.seen_from_behind`).
    # A composed building's rooms are scans placed side by side, and a view across a room's unscanned side sees the
    # next room's walls from behind (the benchmark's renders at their true poses: up to 97 % of their points).
    normals = None if building else cloud.normals
    refine_map = RefineMap(xyz, rgb, cls, fine_voxel_m=rc.fine_voxel_m, coarse_voxel_m=rc.coarse_voxel_m,
                           color_scales_m=rc.color_scales_m, color_weight_m=rc.color_weight_m,
                           stored_target=building, gridded=building, tree_ordered=tree_ordered, normals=normals)
    return RegionIndex(region, refine_map, ViewCheck(refine_map.xyz))


class RegionMaps:
    """The site's regions and their search structures.

    `at(xyz)` is the index of the region a map point lies in (the nearest region's when it lies in none).
    """

    def __init__(self, site: Site, config: LocalizeConfig) -> None:
        self.site = site
        self.config = config
        self.regions = site.regions
        self._lo = np.array([r.bounds[0] for r in self.regions])
        self._hi = np.array([r.bounds[1] for r in self.regions])
        self.storeys = Storeys.of(self.regions)
        self._cache: OrderedDict[str, RegionIndex] = OrderedDict()
        self.built = 0  # regions built so far (a cache miss builds one)
        if len(self.regions) == 1:
            self.index(self.regions[0])

    def __len__(self) -> int:
        return len(self.regions)

    def region_at(self, xyz: np.ndarray) -> Region:
        """The region whose box holds the point xyz ((3,) map frame) seen from above; else the nearest box."""
        return self.regions[int(self.indices_at(np.asarray(xyz, dtype=np.float64)[None])[0])]

    def indices_at(self, xyz: np.ndarray) -> np.ndarray:
        """xyz : (n, 3) map points -> (n,) int index into `regions` of the region each lies in (`region_at`), among
        the regions of its storey (`Storeys`)."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if len(self.regions) == 1:
            return np.zeros(len(xyz), dtype=np.int64)
        p = xyz[:, None, :2]
        # Horizontal distance from each point to each box (0 inside); among boxes at the same distance
        # (overlapping boxes) the one whose centre is nearest.
        gap = np.linalg.norm(np.maximum(np.maximum(self._lo[None, :, :2] - p, p - self._hi[None, :, :2]), 0.0), axis=2)
        centre = np.linalg.norm(0.5 * (self._lo[None, :, :2] + self._hi[None, :, :2]) - p, axis=2)
        if self.storeys.several:
            # Seen from above, a room of another storey holds the point as well (two copies of a room one above the
            # other tie), and its map is not the one the point's view shows: its distance counts the height between
            # them too (a point that lies inside a room's box stays in it, a tall room a storey below its neighbours).
            z = xyz[:, None, 2]
            height = np.maximum(np.maximum(self._lo[None, :, 2] - z, z - self._hi[None, :, 2]), 0.0)
            gap = np.where(self.storeys.elsewhere(xyz[:, 2]), np.hypot(gap, height), gap)
        return np.argmin(gap + 1e-6 * centre / (1.0 + centre), axis=1)

    def at(self, xyz: np.ndarray) -> RegionIndex:
        return self.index(self.region_at(xyz))

    def index(self, region: Region) -> RegionIndex:
        """The structures of `region`, built on first use; the least recently used beyond the cache are dropped."""
        found = self._cache.get(region.id)
        if found is not None:
            self._cache.move_to_end(region.id)
            return found
        found = self._cache[region.id] = build_index(self.site, self.regions, region, self.config)
        self.built += 1
        while len(self._cache) > max(1, self.config.regions.max_cached):
            self._cache.popitem(last=False)
        return found

    def cached(self) -> list[str]:
        """Ids of the regions whose structures are held now, least recently used first."""
        return list(self._cache)
