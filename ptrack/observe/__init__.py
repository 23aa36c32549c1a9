"""What is seen: the pinhole camera, 2D observations (the simulated channel, keypoint files), silhouettes and
point correspondences. Imports only `body` and the leaf utilities."""
