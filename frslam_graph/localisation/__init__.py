"""Localisation on a registered floor plan: :mod:`.relocalisation` (a scan's pose on the plan's
distance field, with its covariance)."""
