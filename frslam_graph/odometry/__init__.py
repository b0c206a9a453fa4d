"""Scan odometry: KISS-ICP fused with wheel odometry (:mod:`.scan_odometry`), the motion model and
SE(2) helpers it uses (:mod:`.motion_model`), and the worker process that runs it one stage ahead
of the backend offline (:mod:`.worker`)."""
