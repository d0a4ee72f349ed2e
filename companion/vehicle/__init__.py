"""Vehicle: the link to the autopilot and the timestamped poses it reports."""
