"""Cameras: projection and view geometry, the per-object pixel figure, extra cameras given on the command line."""
