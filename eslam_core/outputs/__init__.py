"""What a run produces from the map: meshes, their culling to observed space, checkpoints and trajectories."""
