"""Plumbing shared by the command-line entry points (train, evaluate, prepare)."""

from __future__ import annotations

import functools
import sys
from typing import Callable, TypeVar

from shapecorr.errors import ShapeCorrError

#: Exit status of a command that stopped on invalid input (a ShapeCorrError).
EXIT_INVALID_INPUT = 2
#: Exit status after Ctrl-C (128 + SIGINT, the shell convention).
EXIT_INTERRUPTED = 130

F = TypeVar("F", bound=Callable)


def exit_on_user_error(fn: F) -> F:
    """Run ``fn`` and turn input errors and Ctrl-C into short messages and exit codes.

    On a :class:`ShapeCorrError` print ``error: <message>`` to stderr (no traceback) and exit 2; on Ctrl-C
    print one line (completed work is kept) and exit 130.

    Only deliberate input/config errors are caught; genuine bugs keep their traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ShapeCorrError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_INVALID_INPUT)
        except KeyboardInterrupt:
            print("interrupted: what was completed is kept (cache entries and results are written atomically); "
                  "run the same command again to continue", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)

    return wrapper  # type: ignore[return-value]


def user_config_error(err: Exception) -> ShapeCorrError:
    """Wrap an OmegaConf/Hydra config error (missing mandatory value, bad interpolation) as a ConfigError."""
    from shapecorr.errors import ConfigError

    return ConfigError(f"invalid configuration: {err}")
