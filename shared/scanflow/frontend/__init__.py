"""The scan-to-map tracking front end: one `Frontend` per robot, fed deskewed scans.

    from scanflow.frontend import Frontend
    frontend = Frontend(settings)              # FrontendSettings (scanflow.config), per robot
    out = frontend.process(points_m, stamp_s, odom_pose, seq, no_return_m, mount)  # FrontendOutput
    out.pose, out.covariance, out.status, out.inserted ...
    frontend.map (MatchingMap, the robot's map), frontend.trajectory.save_tum(path)
    Frontend(settings, initial_pose=None, grid=prior)  # on a prior map, start searched for
    frontend.set_pose(pose)                    # an operator's pose (ROS's /initialpose)
    FrontendStart(settings).pose, .grid()      # scanflow.frontend.prior: what the settings name
    insert_scan(matching_map, points_m, pose, no_return_m, mount)  # the map insertion (map servers)

See `scanflow.frontend.tracker` for what happens to each scan.
"""

from scanflow.frontend.acceptance import AcceptanceLimits, rejection_reason
from scanflow.frontend.motion_filter import MotionFilter
from scanflow.frontend.prediction import (
    MotionPredictor,
    Prediction,
    PredictionSource,
    compose_odometry_increment,
)
from scanflow.frontend.tracker import (
    ACCEPTED,
    Frontend,
    FrontendOutput,
    FrontendStatus,
    default_settings,
    insert_scan,
    occupancy_params,
)
from scanflow.frontend.trajectory import TrajectoryStore, load_tum, save_tum, tum_text

__all__ = [
    "ACCEPTED",
    "AcceptanceLimits",
    "Frontend",
    "FrontendOutput",
    "FrontendStatus",
    "MotionFilter",
    "MotionPredictor",
    "Prediction",
    "PredictionSource",
    "TrajectoryStore",
    "compose_odometry_increment",
    "default_settings",
    "insert_scan",
    "load_tum",
    "occupancy_params",
    "rejection_reason",
    "save_tum",
    "tum_text",
]
