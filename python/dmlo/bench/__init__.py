"""Side-by-side benchmarks of dmlo against the LiDAR odometry tools people use today."""
