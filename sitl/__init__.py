"""Software in the loop: a mock PX4/ArduPilot autopilot on MAVLink and a rendered camera.

`sitl.runner.Sitl` runs one scenario's mission on loopback (the autopilot in `sitl.autopilot`,
the camera in `sitl.camera` served by `sitl.stream`, the targets in `sitl.world`, the faults of
`sitl.faults`); `companion-sitl` (`sitl.cli`) runs it from the command line.
"""
