"""The built-in simulator: worlds, trajectories, a lidar with true motion distortion, odometry."""
