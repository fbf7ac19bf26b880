"""Offline apps: every stage in one process, over a source or a motion file, results and plots
in a folder: `gridslam odometry` (odometry.py), `gridslam integrate` and `simulate`
(integration.py), `gridslam map` (mapping.py). They stand above the services' cores and import
them; no service imports them."""
