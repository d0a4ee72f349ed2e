"""Flight recording: what a run saw, written as it goes so that it can be replayed."""
