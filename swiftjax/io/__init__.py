"""File formats: images in; trajectories, point clouds, pose graphs and COLMAP models out."""
