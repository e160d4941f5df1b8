"""Grid maps: occupancy in log-odds and the views matchers use (likelihood field, pyramid,
max-pooled grids, NDT cells), plus export and import."""
