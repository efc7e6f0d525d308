"""The peers: the LiDAR odometry tools people use today (KISS-ICP, small_gicp, Open3D) behind DMLO's
frame-by-frame interface, the runner that puts them beside DMLO on the same scans (`dmlo bench`), and the
GICP consensus that stands in for ground truth on real scans."""
