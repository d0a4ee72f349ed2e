"""Planners (pure: robot pose, mixture, tracks, world -> next waypoint)."""
