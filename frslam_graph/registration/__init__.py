"""MFR registration of a floor plan to an occupancy grid."""
