"""Deskew: raw scans + odometry in, motion-compensated scans out (per robot, by wildcard)."""
