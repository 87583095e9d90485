"""The log file of a run (``evaluate.log``, ``train.log`` in its output folder) and plain progress output.

:func:`run_log` copies everything the run prints (stdout and stderr: messages, warnings, progress bars,
errors, the final summary line) and every ``logging`` record into ``<folder>/<name>.log``, appending when a run
resumes in the same folder. In the log, and on a stream that is not a terminal (a redirected file, a batch
system's output), a progress bar's carriage-return updates become one line each, so such output reads as plain
text lines as it happens; ANSI cursor movements are dropped there.

Only rank 0 of a distributed run writes the log. Output of worker processes (``workers=N``) reaches the terminal
but not the log.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import sys
from pathlib import Path

from shapecorr.errors import ConfigError

#: Format of ``logging`` records in the log file.
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


class PlainLines:
    """Turns carriage-return updates into lines (a progress bar's redraws become one line each)."""

    def __init__(self):
        self.at_line_start = True

    def __call__(self, text: str) -> str:
        """``text`` with each carriage return that ends a non-empty line made a newline, ANSI codes removed."""
        text = _ANSI.sub("", text).replace("\r\n", "\n")
        out = []
        for char in text:
            if char == "\r":
                if not self.at_line_start:
                    out.append("\n")
                    self.at_line_start = True
                continue
            out.append(char)
            self.at_line_start = char == "\n"
        return "".join(out)


class Tee(io.TextIOBase):
    """A text stream writing to ``stream`` and, as plain lines, to the ``log`` file object."""

    def __init__(self, stream, log):
        self.stream, self.log = stream, log
        self.terminal = _isatty(stream)
        self._plain_stream, self._plain_log = PlainLines(), PlainLines()

    def write(self, text: str) -> int:
        """Write to both (plain lines to the log, and to the stream when it is not a terminal)."""
        self.stream.write(text if self.terminal else self._plain_stream(text))
        if not self.terminal:
            self.stream.flush()  # a redirected stream shows progress as it happens
        self.log.write(self._plain_log(text))
        self.log.flush()
        return len(text)

    def flush(self) -> None:
        """Flush both."""
        self.stream.flush()
        self.log.flush()

    def isatty(self) -> bool:
        """Whether the stream is a terminal."""
        return self.terminal

    def fileno(self) -> int:
        """The stream's file descriptor."""
        return self.stream.fileno()

    @property
    def encoding(self):
        """The stream's encoding."""
        return getattr(self.stream, "encoding", "utf-8")


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class _LogOnly(io.TextIOBase):
    def __init__(self, log):
        self.log = log

    def write(self, text: str) -> int:
        self.log.write(text)
        self.log.flush()
        return len(text)


def _is_rank_zero() -> bool:
    return os.environ.get("RANK", os.environ.get("LOCAL_RANK", "0")) in ("0", "")


@contextlib.contextmanager
def run_log(folder: str | os.PathLike, name: str):
    """Copy the run's output and logging records to ``<folder>/<name>.log`` while the block runs.

    Raises
    ------
    ConfigError
        The folder cannot be created or the log file cannot be written (the message names it).
    """
    if not _is_rank_zero():
        yield None
        return
    path = Path(folder) / f"{name}.log"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        log = open(path, "a", encoding="utf-8", errors="replace")
    except OSError as err:
        raise ConfigError(f"cannot write the log file ({err.strerror or err}); choose another output folder",
                          path) from None
    handler = logging.StreamHandler(_LogOnly(log))
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    root = logging.getLogger()
    root.addHandler(handler)
    stdout, stderr = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = Tee(stdout, log), Tee(stderr, log)
    try:
        yield path
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        sys.stdout, sys.stderr = stdout, stderr
        root.removeHandler(handler)
        log.close()


def stdout_is_terminal() -> bool:
    """Whether the run's standard output is a terminal (else progress is printed as plain lines)."""
    return _isatty(sys.stdout)
