"""Trajectory evaluation, evo-style: the metrics take arrays and know nothing of files.

- :mod:`~frslam_graph.evaluation.trajectory`: the (N, 4) ``stamp, x, y, theta`` array checked,
  poses matched or interpolated at stamps.
- :mod:`~frslam_graph.evaluation.trajectory_io`: TUM trajectory files and relations files.
- :mod:`~frslam_graph.evaluation.relations`: the relation-based error (Kümmerle et al. 2009).
- :mod:`~frslam_graph.evaluation.metrics`: ATE and RPE through evo, with SE(2) / Sim(2) alignment.
"""
