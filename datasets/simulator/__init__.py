"""2D LiDAR + odometry simulator on real floor plans (true house, distortion, route, ray casting)."""
