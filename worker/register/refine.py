"""Register all scans of a tablet: coarse placement, leave-one-out multi-start ICP guided by
silhouette consistency, then all poses at once on projective point-to-plane correspondences
of every pair (:mod:`worker.register.joint`).

Scans without a height map (bare point clouds) take the earlier fine stage: pairwise
point-to-plane ICP on the overlaps and a global adjustment over all pairs, Open3D's pose
graph (Choi, Zhou & Koltun, "Robust reconstruction of indoor scenes", CVPR 2015, with line
processes that prune inconsistent pairs): nodes are the scan → tablet transforms, edges the
pairwise ICP results weighted by their information matrices (the Gauss-Newton Hessian of
the point-to-plane residuals).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from worker.register.align import (
    FACE_ROTATIONS,
    IcpResult,
    centring_transform,
    cloud_of,
    feature_alignment,
    icp,
    multi_start_icp,
    object_diameter_mm,
)
from worker.register.joint import joint_refine, silhouette_consistency
from worker.register.o3d import o3d, point_cloud, rigid, transform_points
from worker.register.pointcloud import ScanCloud

__all__ = ["PairReport", "Registration", "register_scans"]

_REG = o3d.pipelines.registration
# How far the coarse search may turn a scan from its first placement (pose or face label):
# twice the 20° of a wrong recorded pose that it must correct (issue 8).
MAX_TURN_DEG = 40.0


@dataclass(frozen=True)
class PairReport:
    """A pair of scans after the global adjustment: overlap = fraction of ``a``'s points
    with a point of ``b`` within ``distance_um``; rms_um = RMS of those distances (nearest
    samples, so mostly the lateral spacing of the two samplings); surface_rms_um = RMS
    distance of the points of each to the other's interpolated surface (the misfit itself;
    None for bare point clouds or pairs without projective correspondences)."""

    a: str
    b: str
    overlap: float
    rms_um: float
    distance_um: float
    used: bool
    surface_rms_um: float | None = None


@dataclass(frozen=True)
class Registration:
    """transforms: one 4×4 scan → tablet transform (mm) per scan, in input order;
    init: how each scan was first placed ("pose", "face", "features", "anchor");
    pairs: per-pair reports; restarts: scans whose given pose ICP replaced by a turned start."""

    transforms: list[np.ndarray]
    init: list[str]
    pairs: list[PairReport]
    restarts: list[str] = field(default_factory=list)


def _union(scans, transforms, skip: int, voxel_mm: float) -> o3d.geometry.PointCloud:
    pts, nrm = [], []
    for i, (s, t) in enumerate(zip(scans, transforms, strict=True)):
        if i == skip or t is None:
            continue
        pts.append(transform_points(t, s.points_mm))
        nrm.append(s.normals @ t[:3, :3].T)
    return point_cloud(np.concatenate(pts), np.concatenate(nrm)).voxel_down_sample(voxel_mm)


def _place_without_pose(scans, transforms, k, coarse, voxel, seed) -> tuple[np.ndarray, str]:
    """Best of: the face label's standard orientation, FPFH + RANSAC against the scans
    placed so far; each refined by multi-start ICP."""
    src = cloud_of(scans[k]).voxel_down_sample(voxel)
    target = _union(scans, transforms, k, voxel)
    inits, names = [], []
    if scans[k].face in FACE_ROTATIONS:
        rot = FACE_ROTATIONS[scans[k].face].T
        inits.append(centring_transform(scans[k], rot, placed_mm=_placed_points(scans, transforms)))
        names.append("face")
    inits.append(feature_alignment(src, target, voxel_mm=2.0 * voxel, seed=seed))
    names.append("features")
    res, which = multi_start_icp(src, target, inits, distances_mm=coarse, search_voxel_mm=3 * voxel)
    return res.transform, names[which]


def _initial(scans, coarse, voxel, seed) -> tuple[list[np.ndarray], list[str]]:
    transforms: list[np.ndarray | None] = [None] * len(scans)
    init = [""] * len(scans)
    # Without a pose, a face label is the rotation prior (its standard orientation); the
    # leave-one-out search below corrects it as it corrects a wrong pose.
    rots = [
        s.pose.T
        if s.pose is not None
        else FACE_ROTATIONS[s.face].T
        if s.face in FACE_ROTATIONS
        else None
        for s in scans
    ]
    posed = [(s, r) for s, r in zip(scans, rots, strict=True) if r is not None]
    for i, s in enumerate(scans):  # first the scans whose axes others' silhouettes measure
        if rots[i] is not None:
            others = [(c, r) for c, r in posed if c is not s]
            transforms[i] = centring_transform(s, rots[i], others)
            init[i] = "pose" if s.pose is not None else "face"
    for i, s in enumerate(scans):  # then oblique ones, against the tablet placed so far
        if rots[i] is not None and transforms[i] is None:
            placed = _placed_points(scans, transforms)
            if placed is None:
                raise ValueError(f"{s.label}: cannot place from its pose alone")
            transforms[i] = centring_transform(s, rots[i], placed_mm=placed)
    if all(t is None for t in transforms):
        a = next((i for i, s in enumerate(scans) if s.face == "obverse"), 0)
        rot = FACE_ROTATIONS.get(scans[a].face, np.eye(3)).T
        t = centring_transform(scans[a], rot)
        if t is None:  # nothing measures its depth: centre on its own points
            t = centring_transform(
                scans[a], rot, placed_mm=scans[a].points_mm - scans[a].points_mm.mean(0)
            )
        transforms[a] = t
        init[a] = "anchor"
    for k in range(len(scans)):
        if transforms[k] is None:
            transforms[k], init[k] = _place_without_pose(scans, transforms, k, coarse, voxel, seed)
    return transforms, init


def _placed_points(scans, transforms) -> np.ndarray | None:
    pts = [
        transform_points(t, s.points_mm)
        for s, t in zip(scans, transforms, strict=True)
        if t is not None
    ]
    return np.concatenate(pts) if pts else None


def _leave_one_out(
    scans,
    transforms,
    distances,
    voxel,
    labels_moved,
    tolerance_px=None,
    worst_first=False,
    prior=None,
) -> list[np.ndarray]:
    """Each scan against all the others, coarse to fine from its current transform; then a
    scan that fits far worse than the rest (a recorded pose tens of degrees wrong) is
    searched again from starts turned about 14 axes.

    With height maps (``tolerance_px`` given) "fits" is silhouette consistency
    (:func:`silhouette_consistency`): an ICP move that lowers it is refused (a rounded edge
    is nearly a cylinder, and ICP can slide a scan around it: measured 40–60° on the
    simulator when a neighbour's pose was 20° wrong), a scan below 0.95 is searched (worst
    first, recomputed after each move) and a turned start replaces its pose when it is more
    consistent. Bare point clouds: overlap under half the median, and a turned start must
    overlap half as much again (on reconstructed scans the overlap at 0.7 pixel is a noisy
    measure, and a large face overlaps its neighbours only at its rim)."""
    out = list(transforms)

    def consistency(k, t):
        # A box-like tablet is nearly symmetric: a face turned over, or an edge scan turned a
        # quarter, can fit the silhouettes. The search corrects poses up to ~20° wrong; a
        # candidate beyond MAX_TURN_DEG from the first placement is not one of those.
        if prior is not None and _rotation_deg(t, prior[k]) > MAX_TURN_DEG:
            return -1.0
        return silhouette_consistency(
            scans, [*out[:k], t, *out[k + 1 :]], k, tolerance_px=tolerance_px
        )

    def recentred(k, t):
        """``t``'s rotation, translated so that the scan's extent meets the others' (the
        support function, :func:`centring_transform`): a neighbour's wrong pose can put
        the first placement millimetres off, beyond ICP's reach."""
        others = [u if i != k else None for i, u in enumerate(out)]
        return centring_transform(scans[k], t[:3, :3], placed_mm=_placed_points(scans, others))

    fitness = [0.0] * len(scans)
    order = list(range(len(scans)))
    if worst_first:  # the least consistent first, before it misleads the others
        order.sort(key=lambda k: consistency(k, out[k]))
    for k in order:
        src = cloud_of(scans[k]).voxel_down_sample(voxel)
        target = _union(scans, out, k, voxel)
        res = icp(src, target, out[k], distances_mm=distances, max_iterations=20)
        if tolerance_px is not None:
            # ICP can slide an edge scan around the tablet's rounded rim: the silhouettes
            # choose between ICP's moves and the support-function placement itself.
            moved = recentred(k, out[k])
            alt = icp(src, target, moved, distances_mm=distances, max_iterations=20)
            cands = [out[k], res.transform, moved, alt.transform]
            out[k] = max(cands, key=lambda t: consistency(k, t))
        else:
            out[k] = res.transform
        fitness[k] = res.fitness
    if tolerance_px is None:
        median = float(np.median(fitness))
        for k in np.argsort(fitness):
            if fitness[k] >= 0.5 * median:
                break
            src = cloud_of(scans[k]).voxel_down_sample(voxel)
            target = _union(scans, out, k, voxel)
            res, _ = multi_start_icp(
                src,
                target,
                [out[k]],
                distances_mm=distances,
                search_voxel_mm=2 * voxel,
                min_gain=0.0,
            )
            if res.fitness > 1.5 * fitness[k]:
                labels_moved.append(scans[k].label)
                out[k] = res.transform
        return out
    tried: set[int] = set()
    while True:
        values = {k: consistency(k, out[k]) for k in range(len(scans)) if k not in tried}
        k = min(values, key=values.get) if values else None
        if k is None or values[k] >= 0.95:
            return out
        tried.add(k)
        src = cloud_of(scans[k]).voxel_down_sample(voxel)
        target = _union(scans, out, k, voxel)
        res, _ = multi_start_icp(
            src,
            target,
            [out[k], recentred(k, out[k])],
            distances_mm=distances,
            search_voxel_mm=2 * voxel,
            min_gain=0.0,
            score=lambda t, k=k: consistency(k, t),
            dense=True,
        )
        if consistency(k, res.transform) > values[k]:
            labels_moved.append(scans[k].label)
            out[k] = res.transform


def _polish(scans, clouds, transforms, distance_mm, rounds) -> list[np.ndarray]:
    """Each scan at full density against all the others at full density (no thinning: the
    overlaps are narrow bands a few samples wide), at the finest distance. The pose graph's
    pairwise edges each see one band; the union of all others constrains every direction
    at once (measured: 0.08° → 0.03° largest relative rotation error on the simulator)."""
    out = list(transforms)
    for _ in range(rounds):
        for k in range(len(scans)):
            others = [
                transform_points(t, s.points_mm)
                for i, (s, t) in enumerate(zip(scans, out, strict=True))
                if i != k
            ]
            normals = [
                s.normals @ t[:3, :3].T
                for i, (s, t) in enumerate(zip(scans, out, strict=True))
                if i != k
            ]
            target = point_cloud(np.concatenate(others), np.concatenate(normals))
            out[k] = icp(clouds[k], target, out[k], distances_mm=(distance_mm,)).transform
    return out


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def _pairwise(clouds, transforms, distances_mm, min_overlap):
    edges = []
    for i in range(len(clouds)):
        for j in range(i + 1, len(clouds)):
            init = np.linalg.inv(transforms[j]) @ transforms[i]
            ev = _REG.evaluate_registration(clouds[i], clouds[j], distances_mm[0], init)
            if ev.fitness < min_overlap:
                continue  # opposite faces: no overlap, no edge
            res = icp(clouds[i], clouds[j], init, distances_mm=distances_mm, max_iterations=20)
            distance_mm = distances_mm[-1]
            if res.fitness >= min_overlap:
                info = _REG.get_information_matrix_from_point_clouds(
                    clouds[i], clouds[j], distance_mm, res.transform
                )
                edges.append((i, j, res, info))
    return edges


def _pose_graph(transforms, edges, anchor, distance_mm) -> list[np.ndarray]:
    graph = _REG.PoseGraph()
    for t in transforms:
        graph.nodes.append(_REG.PoseGraphNode(np.array(t)))
    for i, j, res, info in edges:
        graph.edges.append(_REG.PoseGraphEdge(i, j, res.transform, info, uncertain=True))
    option = _REG.GlobalOptimizationOption(
        max_correspondence_distance=distance_mm,
        edge_prune_threshold=0.25,
        preference_loop_closure=1.0,
        reference_node=anchor,
    )
    _REG.global_optimization(
        graph,
        _REG.GlobalOptimizationLevenbergMarquardt(),
        _REG.GlobalOptimizationConvergenceCriteria(),
        option,
    )
    return [np.array(n.pose) for n in graph.nodes]


def register_scans(
    scans: list[ScanCloud],
    *,
    rounds: int = 2,
    loo_rounds: int = 2,
    min_overlap: float = 0.01,
    seed: int = 0,
) -> Registration:
    """Register ``scans`` (at least two) into one tablet frame.

    1. Place each scan: from ``pose`` (centred, :func:`centring_transform`), else by the face
       label's standard orientation or FPFH features, whichever ICP fits best.
    2. ``loo_rounds`` × each scan against the union of the others (:func:`_leave_one_out`):
       with height maps coarse only (1/25 of the tablet → 2 voxels), guided by silhouette
       consistency, which also finds a recorded pose tens of degrees wrong and searches it
       again from starts turned by 20° about 26 axes; bare clouds down to 0.7 pixel, by
       overlap, 14 axes.
    3. With height maps: all poses at once on projective point-to-plane correspondences,
       gates 8 → 1 pixel (:func:`worker.register.joint.joint_refine`). Bare clouds:
       ``rounds`` × pairwise ICP on every overlapping pair (fitness ≥ ``min_overlap``) at
       0.7 pixel, then the pose graph over all pairs; then ``rounds`` × each scan against
       all others at full density and 0.7 pixel (:func:`_polish`).
    4. The tablet frame's origin is put at the centre of the registered points' bounding box;
       its orientation is that of the poses (or of the anchor scan's face).
    """
    if len(scans) < 2:
        raise ValueError("scans: need at least two scans to register")
    labels = [s.label for s in scans]
    if len(set(labels)) != len(labels):
        raise ValueError(f"scans: labels must be unique, got {labels}")
    diameter = object_diameter_mm(scans)
    pixel_mm = max(s.pixel_size_um for s in scans) / 1000.0
    voxel = max(diameter / 150.0, pixel_mm)
    coarse = (diameter / 12.0, diameter / 30.0, diameter / 80.0)
    transforms, init = _initial(scans, coarse, voxel, seed)
    restarted: list[str] = []
    # Correspondences farther apart than about a pixel pair points beside, not on, the overlap
    # and pull the scans into each other's gaps: the last distance is 0.7 pixel.
    fine_mm = 0.7 * pixel_mm
    grids = all(s.grid is not None for s in scans)
    if grids:  # coarse only, on thinned clouds: the projective refinement does the fine part
        loo, loo_voxel = (diameter / 25.0, 4.0 * voxel, 2.0 * voxel), 2.0 * voxel
    else:
        loo, loo_voxel = (diameter / 25.0, 4.0 * pixel_mm, 2.0 * pixel_mm, fine_mm), pixel_mm
    # Silhouettes are compared to within the coarse stage's accuracy, a few sample spacings.
    tolerance_px = 4.0 * voxel / pixel_mm if grids else None
    if grids:
        # Two orders of the pass (as given; least consistent first): a wrong pose can mislead
        # the neighbours processed before it, or be handled before its neighbours have found
        # their places. The outcome whose least consistent scan is most consistent is kept.
        # The second order only runs when the first leaves a scan inconsistent.
        outcomes = []
        for worst_first in (False, True):
            moved: list[str] = []
            t = list(transforms)
            for _ in range(loo_rounds):
                t = _leave_one_out(
                    scans, t, loo, loo_voxel, moved, tolerance_px, worst_first, transforms
                )
            worst = min(
                silhouette_consistency(scans, t, k, tolerance_px=tolerance_px)
                for k in range(len(scans))
            )
            outcomes.append((worst, t, moved))
            if worst >= 0.95:
                break
        transforms = max(outcomes, key=lambda o: o[0])[1]
    else:
        for _ in range(loo_rounds):
            transforms = _leave_one_out(scans, transforms, loo, loo_voxel, restarted)
    clouds = [cloud_of(s) for s in scans]
    anchor = next((i for i, how in enumerate(init) if how in ("anchor", "pose")), 0)
    if "pose" not in init:  # no pose at all: the obverse (else the first) scan is the anchor
        anchor = next((i for i, s in enumerate(scans) if s.face == "obverse"), 0)
    surface_rms: dict = {}
    if grids:
        # Height maps: all poses at once on projective correspondences (worker.register.joint).
        # From each coarse outcome (two when the first order left a scan inconsistent): the
        # fine stage can slide an edge scan that starts a few degrees off along its nearly
        # free roll into a second minimum, which its silhouette (to 2 pixels) then betrays.
        finals = []
        for _, start, moved in outcomes:
            t, stats = joint_refine(
                scans,
                start,
                anchor=anchor,
                gates_mm=(8.0 * pixel_mm, 4.0 * pixel_mm, 2.0 * pixel_mm, pixel_mm),
            )
            worst = min(
                silhouette_consistency(scans, t, k, tolerance_px=2.0) for k in range(len(scans))
            )
            finals.append((worst, t, stats, moved))
        _, transforms, surface_rms, moved = max(finals, key=lambda f: f[0])
        restarted.extend(moved)
        index = {s.label: i for i, s in enumerate(scans)}
        used = {tuple(sorted((index[a], index[b]))) for a, b in surface_rms}
    else:  # bare point clouds: pairwise ICP, pose graph, polish
        edges = []
        for _ in range(rounds):
            edges = _pairwise(clouds, transforms, (fine_mm,), min_overlap)
            transforms = _pose_graph(transforms, edges, anchor, fine_mm)
        transforms = _polish(scans, clouds, transforms, fine_mm, rounds)
        used = {(i, j) for i, j, _, _ in edges}
    all_pts = np.concatenate(
        [transform_points(t, s.points_mm) for s, t in zip(scans, transforms, strict=True)]
    )
    centre = 0.5 * (all_pts.min(axis=0) + all_pts.max(axis=0))
    transforms = [rigid(np.eye(3), -centre) @ t for t in transforms]
    pairs = _reports(clouds, transforms, labels, fine_mm, used, surface_rms)
    return Registration(transforms, init, pairs, sorted(set(restarted)))


def _surface_rms(stats: dict, a: str, b: str) -> float | None:
    """RMS point-to-surface distance (µm) of the pair's projective correspondences, both
    ways, weighted by their counts; None without any."""
    got = [stats[k] for k in ((a, b), (b, a)) if k in stats]
    n = sum(c for c, _ in got)
    if not n:
        return None
    return round(float(np.sqrt(sum(c * r * r for c, r in got) / n)), 2)


def _reports(clouds, transforms, labels, distance_mm, used, surface_rms) -> list[PairReport]:
    out = []
    for i in range(len(clouds)):
        for j in range(i + 1, len(clouds)):
            rel = np.linalg.inv(transforms[j]) @ transforms[i]
            ev = _REG.evaluate_registration(clouds[i], clouds[j], distance_mm, rel)
            res = IcpResult(rel, float(ev.fitness), float(ev.inlier_rmse))
            if res.fitness <= 0:
                continue
            out.append(
                PairReport(
                    labels[i],
                    labels[j],
                    round(res.fitness, 4),
                    round(res.rmse_mm * 1000.0, 2),
                    round(distance_mm * 1000.0, 1),
                    (i, j) in used,
                    _surface_rms(surface_rms, labels[i], labels[j]),
                )
            )
    return out
