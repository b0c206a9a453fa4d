"""Recording readers (CARMEN, ROS 1/2 bags, PCD/PLY folders, simulator output) and the 2D LiDAR simulator."""
from frslam_graph.datasets.scan import Scan

__all__ = ["Scan"]
