"""Adapters for the peer libraries (Open3D, small_gicp) on 2D scan pairs, for bench.matching.

Every adapter takes (source (N,2), target (M,2), guess Pose2D T_target_source) and returns the
estimated Pose2D. The 3D libraries get the 2D points as 3D clouds; plane ICP and the GICP family
need a non-degenerate 3D neighbourhood (a flat slice has no usable covariance or normal), so for
them each 2D point is extruded into three copies at z = -0.1, 0, +0.1 m. The result's rotation
is projected back to the plane (yaw = atan2(R10, R00)). Peers are optional (pip install -e
.[bench]): `load_peers()` gives those whose library imports and, for the others, why not.
Open3D's wheel needs libusb-1.0 from the system (Debian: apt-get install libusb-1.0-0).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scanflow.geometry import Pose2D

PeerFn = Callable[[NDArray[np.float64], NDArray[np.float64], Pose2D], Pose2D]
EXTRUDE_Z_M = (-0.1, 0.0, 0.1)
MAX_CORRESPONDENCE_M = 1.0
MAX_ITERATIONS = 30
NORMAL_RADIUS_M = 0.5
NORMAL_NEIGHBOURS = 10


def to_3d(points: NDArray[np.float64], extrude: bool) -> NDArray[np.float64]:
    """(N, 2) -> (N, 3) at z = 0, or (3N, 3) copies at EXTRUDE_Z_M when `extrude`."""
    zs = EXTRUDE_Z_M if extrude else (0.0,)
    return np.vstack([np.column_stack((points, np.full(len(points), z))) for z in zs])


def pose_to_matrix4(pose: Pose2D) -> NDArray[np.float64]:
    """The 4x4 homogeneous transform of a planar pose (rotation about z, z = 0)."""
    m = np.eye(4)
    m[:2, :2] = pose.rotation_matrix()
    m[:2, 3] = (pose.x, pose.y)
    return m


def matrix4_to_pose(m: NDArray[np.float64]) -> Pose2D:
    """The planar pose of a 4x4 transform: its x, y and yaw atan2(R10, R00)."""
    return Pose2D(float(m[0, 3]), float(m[1, 3]), math.atan2(m[1, 0], m[0, 0]))


def _open3d_peers() -> dict[str, PeerFn]:
    import open3d as o3d

    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(max_iteration=MAX_ITERATIONS)

    def cloud(points: NDArray[np.float64], extrude: bool) -> o3d.geometry.PointCloud:
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(to_3d(points, extrude)))

    def point_to_point(src: NDArray, tgt: NDArray, guess: Pose2D) -> Pose2D:
        r = reg.registration_icp(
            cloud(src, False), cloud(tgt, False), MAX_CORRESPONDENCE_M, pose_to_matrix4(guess),
            reg.TransformationEstimationPointToPoint(), criteria,
        )
        return matrix4_to_pose(np.asarray(r.transformation))

    def point_to_plane(src: NDArray, tgt: NDArray, guess: Pose2D) -> Pose2D:
        t = cloud(tgt, True)
        t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(NORMAL_RADIUS_M, NORMAL_NEIGHBOURS))
        r = reg.registration_icp(
            cloud(src, True), t, MAX_CORRESPONDENCE_M, pose_to_matrix4(guess),
            reg.TransformationEstimationPointToPlane(), criteria,
        )
        return matrix4_to_pose(np.asarray(r.transformation))

    def gicp(src: NDArray, tgt: NDArray, guess: Pose2D) -> Pose2D:
        r = reg.registration_generalized_icp(
            cloud(src, True), cloud(tgt, True), MAX_CORRESPONDENCE_M, pose_to_matrix4(guess),
            reg.TransformationEstimationForGeneralizedICP(), criteria,
        )
        return matrix4_to_pose(np.asarray(r.transformation))

    return {"open3d-icp": point_to_point, "open3d-plane": point_to_plane, "open3d-gicp": gicp}


def _small_gicp_peers() -> dict[str, PeerFn]:
    import small_gicp

    def make(kind: str, extrude: bool) -> PeerFn:
        def run(src: NDArray, tgt: NDArray, guess: Pose2D) -> Pose2D:
            r = small_gicp.align(
                to_3d(tgt, extrude), to_3d(src, extrude), pose_to_matrix4(guess),
                registration_type=kind, downsampling_resolution=0.01,
                voxel_resolution=0.5, max_correspondence_distance=MAX_CORRESPONDENCE_M,
                num_threads=1, max_iterations=MAX_ITERATIONS,
            )
            return matrix4_to_pose(np.asarray(r.T_target_source))

        return run

    return {
        "small_gicp-icp": make("ICP", False),
        "small_gicp-plane": make("PLANE_ICP", True),
        "small_gicp-gicp": make("GICP", True),
        "small_gicp-vgicp": make("VGICP", True),
    }


LIBRARIES: dict[str, Callable[[], dict[str, PeerFn]]] = {
    "open3d": _open3d_peers,
    "small_gicp": _small_gicp_peers,
}


class Peers(NamedTuple):
    """The peers whose library loaded, by name, and why each other library did not load."""

    found: dict[str, PeerFn]
    missing: dict[str, str]  # library -> the import error, e.g. a system library it lacks


def load_peers() -> Peers:
    """Every peer of every library that imports. A library that is installed but cannot load
    (Open3D without libusb-1.0 on the machine, say) is reported with its error, not dropped
    silently from the comparison."""
    found: dict[str, PeerFn] = {}
    missing: dict[str, str] = {}
    for library, loader in LIBRARIES.items():
        try:
            found.update(loader())
        except ImportError as exc:  # OSError from a missing .so surfaces as ImportError
            missing[library] = f"{type(exc).__name__}: {exc}"
    return Peers(found, missing)
