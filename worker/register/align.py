"""Coarse alignment of scans into the tablet frame: from scan.pose, from the face label, or
from FPFH features with RANSAC; then ICP from several starting rotations (multi-start).

Transforms are 4×4 rigid matrices T that map a scan's points (mm, scan frame) into the
tablet frame: X_tablet = R·X_scan + t. ``scan.pose`` is the rotation tablet → scan, so its
transpose is R.

The tablet frame is the one of ``scan.pose`` (and of the simulator): the obverse faces −z,
x runs to the right of the obverse and y down it. ``FACE_ROTATIONS`` gives the standard
rotation tablet → scan of each face in that frame (the simulator's ``FACE_POSES``); it is
the prior used for a scan without a pose.

Features: Rusu, Blodow & Beetz, "Fast Point Feature Histograms (FPFH) for 3D registration",
ICRA 2009, matched with RANSAC (Open3D ``registration_ransac_based_on_feature_matching``).
ICP: point-to-plane (Chen & Medioni 1992) with a Tukey robust kernel so that points outside
the overlap do not pull (Open3D ``TransformationEstimationPointToPlane(TukeyLoss)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from worker.register.o3d import o3d, point_cloud, rigid, transform_points
from worker.register.pointcloud import ScanCloud

__all__ = [
    "FACE_ROTATIONS",
    "IcpResult",
    "centring_transform",
    "feature_alignment",
    "icp",
    "multi_start_icp",
    "object_diameter_mm",
]

FACE_ROTATIONS: dict[str, np.ndarray] = {
    "obverse": np.eye(3),
    "reverse": np.diag([-1.0, 1.0, -1.0]),
    "top": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "bottom": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "left": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "right": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class IcpResult:
    """transform: 4×4 source → target; fitness: fraction of source points with a target point
    within the correspondence distance (the overlap); rmse_mm: RMS of those distances."""

    transform: np.ndarray
    fitness: float
    rmse_mm: float


def object_diameter_mm(clouds: list[ScanCloud]) -> float:
    """Largest extent of any scan's points along any scan axis (mm): the object's size."""
    return float(max(np.ptp(c.points_mm, axis=0).max() for c in clouds))


def centring_transform(
    cloud: ScanCloud,
    rotation_scan_to_tablet: np.ndarray,
    others: list[tuple[ScanCloud, np.ndarray]] = (),
    placed_mm: np.ndarray | None = None,
) -> np.ndarray | None:
    """T with the given rotation R that puts the tablet's centre at the origin.

    X_scan = Rᵀ(X_tablet − t) gives, along each scan axis e_k with u = R·e_k (tablet frame),
    min_k(X_scan) = −h(−u) − (Rᵀt)_k, h the tablet's support function h(v) = max v·X. The
    minima are seen: along x and y they are the silhouette's (exact in an orthographic view),
    along z the nearest visible point. h(−u) comes from ``placed_mm`` (tablet-frame points of
    scans already placed) when given, else from the tablet's extent along u, ½·ptp, seen in
    the silhouette of any scan (this one or ``others``: (cloud, rotation) pairs) whose image
    plane contains u (assumes the tablet is about as far out on both sides of its centre).
    None when some axis has no such scan.
    """
    r = np.asarray(rotation_scan_to_tablet, dtype=np.float64)
    p = cloud.points_mm
    views = [(cloud, r), *others]
    shift = np.zeros(3)
    for k in range(3):
        u = r[:, k]  # scan axis k in the tablet frame
        if placed_mm is not None:
            support = float(np.max(placed_mm @ -u))
        else:
            extents = [
                float(np.ptp(c.points_mm @ (rj.T @ u)))
                for c, rj in views
                if abs((rj.T @ u)[2]) < 0.15
            ]
            if not extents:
                return None
            support = 0.5 * max(extents)
        shift[k] = p[:, k].min() + support
    return rigid(r, -r @ shift)


def icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    *,
    distances_mm: tuple[float, ...],
    max_iterations: int = 40,
) -> IcpResult:
    """Coarse-to-fine point-to-plane ICP (target needs normals), Tukey kernel of width
    ``d/2`` at each correspondence distance ``d``; fitness and RMS at the last distance."""
    t = np.asarray(init, dtype=np.float64)
    crit = _REG.ICPConvergenceCriteria(
        relative_fitness=1e-8, relative_rmse=1e-8, max_iteration=max_iterations
    )
    for d in distances_mm:
        est = _REG.TransformationEstimationPointToPlane(_REG.TukeyLoss(k=d / 2.0))
        t = _REG.registration_icp(source, target, d, t, est, crit).transformation
    ev = _REG.evaluate_registration(source, target, distances_mm[-1], t)
    return IcpResult(np.array(t), float(ev.fitness), float(ev.inlier_rmse))


def _start_rotations(angle_deg: float, dense: bool = False) -> list[np.ndarray]:
    """Identity, then rotations by ``angle_deg`` about the 6 signed axes and 8 diagonals
    (``dense``: also the 12 face diagonals, so that no axis is more than ~20° from one)."""
    axes = [np.array(a, float) for a in np.eye(3)]
    axes += [-a for a in axes]
    axes += [
        np.array([sx, sy, sz]) / np.sqrt(3) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)
    ]
    if dense:
        for i, j in ((0, 1), (0, 2), (1, 2)):
            for si in (1, -1):
                for sj in (1, -1):
                    a = np.zeros(3)
                    a[i], a[j] = si, sj
                    axes.append(a / np.sqrt(2))
    out = [np.eye(3)]
    out += [Rotation.from_rotvec(np.radians(angle_deg) * a).as_matrix() for a in axes]
    return out


def multi_start_icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    inits: list[np.ndarray],
    *,
    distances_mm: tuple[float, ...],
    search_voxel_mm: float,
    angle_deg: float = 20.0,
    min_gain: float = 0.03,
    score=None,
    dense: bool = False,
) -> tuple[IcpResult, int]:
    """ICP from each of ``inits`` and from each init turned by ``angle_deg`` about 14 axes
    through the source's centroid, searched on clouds thinned to ``search_voxel_mm`` with the
    distances but the last; the start with the largest overlap (fitness), which must beat the
    first init's by ``min_gain`` to replace it (a correct pose should stay), is then refined
    at full density with the last distance. ``score`` (transform → float, larger is better)
    replaces the fitness as the measure of a start when given; ``dense`` adds the 12 face
    diagonals to the axes.

    Returns the refined result and the index of the winning init.
    """
    src = source.voxel_down_sample(search_voxel_mm)
    tgt = target.voxel_down_sample(search_voxel_mm)
    centroid = np.asarray(src.points).mean(axis=0)
    first: IcpResult | None = None
    best: tuple[IcpResult, int, float] | None = None
    for k, init in enumerate(inits):
        c = transform_points(init, centroid[None])[0]
        for r in _start_rotations(angle_deg, dense):
            start = rigid(r, c - r @ c) @ init
            res = icp(src, tgt, start, distances_mm=distances_mm[:-1], max_iterations=15)
            value = res.fitness if score is None else float(score(res.transform))
            if first is None:
                first = res
                best = (res, k, value)
            elif value > best[2] + (min_gain if best[0] is first else 0.0):
                best = (res, k, value)
    assert best is not None
    refined = icp(source, target, best[0].transform, distances_mm=distances_mm[-1:])
    return refined, best[1]


def _fpfh(pcd: o3d.geometry.PointCloud, voxel_mm: float):
    return _REG.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel_mm, max_nn=100)
    )


def feature_alignment(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    *,
    voxel_mm: float,
    seed: int = 0,
) -> np.ndarray:
    """A 4×4 source → target transform from FPFH features matched by RANSAC; needs no pose.

    Both clouds need normals; they are voxel-downsampled to ``voxel_mm`` first.
    """
    if voxel_mm <= 0:
        raise ValueError(f"voxel_mm must be > 0, got {voxel_mm!r}")
    src = source.voxel_down_sample(voxel_mm)
    tgt = target.voxel_down_sample(voxel_mm)
    o3d.utility.random.seed(seed)
    dist = 1.5 * voxel_mm
    result = _REG.registration_ransac_based_on_feature_matching(
        src,
        tgt,
        _fpfh(src, voxel_mm),
        _fpfh(tgt, voxel_mm),
        True,
        dist,
        _REG.TransformationEstimationPointToPoint(False),
        3,
        [
            _REG.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            _REG.CorrespondenceCheckerBasedOnDistance(dist),
        ],
        _REG.RANSACConvergenceCriteria(200000, 0.9999),
    )
    return np.array(result.transformation)


def cloud_of(scan: ScanCloud, transform: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """The scan as an Open3D cloud, optionally moved by ``transform`` (normals rotated)."""
    if transform is None:
        return point_cloud(scan.points_mm, scan.normals, scan.colours)
    t = np.asarray(transform)
    return point_cloud(
        transform_points(t, scan.points_mm), scan.normals @ t[:3, :3].T, scan.colours
    )
