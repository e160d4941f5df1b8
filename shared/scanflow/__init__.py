"""scanflow: a 2D LiDAR pipeline core (deskewing, scan matching, grid maps, tracking).

The core is pure: no network, no bus, no web framework. Services under `services/` wrap it.
"""

__version__ = "0.1.0"
