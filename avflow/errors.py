"""Exceptions of avflow.

Every problem with the input is a :class:`ScenarioError`: one line per problem, each naming
the file, the line:column where the value was written and the dotted field, in the form
compilers use (editors turn it into a link)::

    scenarios/foo.yaml:14:3: rheology.delta_deg: must be in [0, 90) degrees, got 95.0
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Iterable


class AvflowError(Exception):
    """Base class of the errors avflow reports to its users (the CLI exits with code 2)."""

    exit_code = 2  #: of the command line: 2 bad input


#: The signals (SIGINT, SIGTERM) the command was sent, noted by its handler before it raises
#: KeyboardInterrupt: an interrupt that code in between swallowed (a finalizer, a library's
#: ``except``) is not lost: :func:`check_interrupted` raises it again where work is handed
#: out, and the command ends as interrupted.
INTERRUPTS: list = []


def check_interrupted() -> None:
    """Raise KeyboardInterrupt if the command was interrupted (see :data:`INTERRUPTS`)."""
    if INTERRUPTS:
        raise KeyboardInterrupt


class AvflowWarning(UserWarning):
    """Something a user should know that does not stop the command (the command line prints
    it as one ``avflow: warning:`` line)."""


class RunFailed(AvflowError):
    """A run that failed numerically: a non-finite state (h, hu, hv or the mass balance),
    or no time step that keeps h >= 0. Never a result: the command line writes no output
    file and exits with code 1; ``result`` holds the run up to the failure (in process only).
    """

    exit_code = 1

    def __init__(self, message: str, result: Any = None):
        super().__init__(message)
        self.result = result


@dataclass(frozen=True)
class Problem:
    """One problem in a scenario: where it is (all optional) and what is wrong."""

    message: str
    path: str | None = None  #: the scenario file
    field: str | None = None  #: dotted field, e.g. ``"rheology.delta_deg"``
    line: int | None = None  #: 1-based
    column: int | None = None  #: 1-based

    def __str__(self) -> str:
        where = _shown(self.path) if self.path else "<scenario>"
        if self.line is not None:
            where += f":{self.line}"
            if self.column is not None:
                where += f":{self.column}"
        field = f"{self.field}: " if self.field else ""
        return f"{where}: {field}{self.message}"


class ScenarioError(AvflowError):
    """A scenario that cannot be read or is invalid.

    ``path``, ``field``, ``line``, ``column`` and ``message`` describe the first problem;
    ``problems`` holds all of them (pydantic may report several at once), one per line in
    ``str(error)``.
    """

    def __init__(self, message: str = "", path: str | os.PathLike | None = None,
                 field: str | None = None, line: int | None = None, column: int | None = None,
                 *, problems: Iterable[Problem] = ()):
        path = os.fspath(path) if path is not None else None
        problems = tuple(problems) or (Problem(message, path, field, line, column),)
        first = problems[0]
        self.problems: tuple[Problem, ...] = problems
        self.path, self.field = first.path, first.field
        self.line, self.column, self.message = first.line, first.column, first.message
        super().__init__("\n".join(str(p) for p in problems))

    def __reduce__(self):
        # An exception pickles as ``cls(*args)``, which would lose the fields: rebuild it from
        # its problems instead (dask sends errors between processes).
        return _rebuild, (type(self), self.problems)

    @classmethod
    def at(cls, scenario: Any, field: str | None, message: str) -> ScenarioError:
        """An error about ``field`` of an already validated scenario.

        For problems found after validation (a release outside the domain, a DEM that does
        not cover the release...). The line and column are those of the field in the
        scenario's file when it was loaded from one (or of its closest written parent).
        """
        locate = getattr(scenario, "locate", None)
        line, column = (locate(field) if locate and field else None) or (None, None)
        return cls(message, getattr(scenario, "source_path", None), field, line, column)


def _rebuild(cls: type[ScenarioError], problems: tuple[Problem, ...]) -> ScenarioError:
    return cls(problems=problems)


def _shown(path: str) -> str:
    """``path`` relative to the working directory when it lies inside it (shorter messages)."""
    if not os.path.isabs(path):
        return path
    try:
        relative = os.path.relpath(path)
    except ValueError:  # another drive on Windows
        return path
    return path if relative.startswith(os.pardir) else relative
