"""What the commands of ``abmpm`` share: exit codes, the consoles, the port argument and the threads check
(the count types are in ``arguments.py``, which ``abmpm bench`` shares)."""

from __future__ import annotations

from rich.console import Console
from rich.markup import escape

from abmpm.arguments import int_between
from abmpm.errors import AbmpmError
from abmpm.sim.parallel import default_threads

EXIT_OK = 0
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


def stdout_console() -> Console:
    """Results (tables, the summary) go to stdout."""
    return Console(highlight=False)


def stderr_console() -> Console:
    """Progress and messages go to stderr."""
    return Console(stderr=True, highlight=False)


def esc(text) -> str:
    """User text (paths, names, messages) printed through rich: '[' is not markup."""
    return escape(str(text))


def check_threads_env() -> None:
    """AbmpmError for an ABMPM_THREADS that is not a number of threads."""
    try:
        default_threads()
    except ValueError as exc:
        raise AbmpmError(str(exc)) from None


def port_arg(text: str) -> int:
    """--port N: 0 (any free port) to 65535."""
    return int_between(text, "a port number", 0, 65535)
