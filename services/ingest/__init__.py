"""Ingest: publish scans and odometry from a log or the simulator, paced, with backpressure."""
