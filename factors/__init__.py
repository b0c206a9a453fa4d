"""Floor-plan priors and odometry between-factors for the GTSAM Pose2 graph (metres, radians)."""
