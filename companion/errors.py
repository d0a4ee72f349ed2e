"""The project's one error hierarchy: every error a user can meet is a CompanionError."""

from __future__ import annotations


class CompanionError(Exception):
    """Root of every error the project raises on purpose."""


class ConfigError(CompanionError):
    """A configuration or scenario value is missing, of the wrong type or out of range."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem


class InputError(CompanionError):
    """Data handed to the core (measurements, poses, covariances, regions) is unusable."""
