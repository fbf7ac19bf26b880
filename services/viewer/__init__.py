"""The live viewer: a browser page showing a run's trajectories, map, lattice and camera."""
