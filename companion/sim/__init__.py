"""Filter-only simulation: scenario files, simulated world and sensor, the run loop."""
