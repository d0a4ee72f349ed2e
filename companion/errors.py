"""The project's one error hierarchy: every error a user can meet is a CompanionError."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")


class CompanionError(Exception):
    """Root of every error the project raises on purpose."""


class ConfigError(CompanionError):
    """A configuration or scenario value is missing, of the wrong type or out of range."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem

    @property
    def errors(self) -> tuple[ConfigError, ...]:
        """The single errors this one stands for: itself."""
        return (self,)


class AggregateConfigError(ConfigError):
    """Several ConfigErrors of one file; str lists one "key: problem" line each, first first."""

    def __init__(self, errors: Iterable[ConfigError]) -> None:
        singles = tuple(single for e in errors for single in e.errors)
        if not singles:
            raise ValueError("AggregateConfigError needs at least one error")
        super().__init__(singles[0].key, singles[0].problem)
        self.args = ("\n".join(str(e) for e in singles),)
        self._errors = singles

    def __str__(self) -> str:
        return str(self.args[0])

    @property
    def errors(self) -> tuple[ConfigError, ...]:
        """Every single error, in the order found."""
        return self._errors


class ErrorCollector:
    """Gathers the ConfigErrors of several independent checks, to report them all at once."""

    def __init__(self) -> None:
        self.found: list[ConfigError] = []

    def attempt(self, check: Callable[[], T]) -> T | None:
        """check()'s value, or None after recording the ConfigError(s) it raised."""
        try:
            return check()
        except ConfigError as exc:
            self.found.extend(exc.errors)
            return None

    def add(self, error: ConfigError) -> None:
        """Record one more error."""
        self.found.extend(error.errors)

    def raise_any(self) -> None:
        """Raise the one error found as itself, several as AggregateConfigError, or nothing."""
        if len(self.found) == 1:
            raise self.found[0]
        if self.found:
            raise AggregateConfigError(self.found)


class InputError(CompanionError):
    """Data handed to the core (measurements, poses, covariances, regions) is unusable.

    `reason` is the message without its subject, for a caller that names the key itself;
    `field`, when given, is the core's own name of the unusable argument.
    """

    def __init__(self, message: str, *, reason: str | None = None,
                 field: str | None = None) -> None:
        super().__init__(message)
        self.reason = message if reason is None else reason
        self.field = field


def field_error(field: str, reason: str) -> InputError:
    """An InputError about one named argument of the core: "<field> <reason>"."""
    return InputError(f"{field} {reason}", reason=reason, field=field)
