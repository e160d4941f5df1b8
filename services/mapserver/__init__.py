"""Map server: builds each robot's occupancy map from deskewed scans and published poses."""
