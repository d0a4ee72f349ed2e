"""Speed and reliability measurements of the service (scripts; not installed)."""
