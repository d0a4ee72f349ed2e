"""Software in the loop: the mock autopilot and rendered camera (to come with the SITL work)."""
