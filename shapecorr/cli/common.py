"""Plumbing shared by the command-line entry points (train, evaluate, prepare)."""

from __future__ import annotations

import errno
import functools
import sys
import tempfile
import threading
from pathlib import Path
from typing import Callable, TypeVar

from hydra.experimental.callback import Callback

from shapecorr.errors import ShapeCorrError

#: Exit status of a command that stopped on invalid input (a ShapeCorrError).
EXIT_INVALID_INPUT = 2
#: Exit status after Ctrl-C (128 + SIGINT, the shell convention).
EXIT_INTERRUPTED = 130

F = TypeVar("F", bound=Callable)


def exit_on_user_error(fn: F) -> F:
    """Run ``fn`` and turn input errors and Ctrl-C into short messages and exit codes.

    On a :class:`ShapeCorrError` print ``error: <message>`` to stderr (no traceback) and exit 2; on Ctrl-C
    print one line (completed work is kept) and exit 130; on a storage fault (:data:`STORAGE_ERRNOS`: disk full,
    permission denied, read-only file system, ...) print the file, the fault and how to continue, and exit 2.

    Only deliberate input/config errors are caught; genuine bugs keep their traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        previous_hook = threading.excepthook

        def storage_fault_in_thread(args) -> None:  # e.g. TensorBoard's writer thread on a full disk: one line
            if isinstance(args.exc_value, OSError) and args.exc_value.errno in STORAGE_ERRNOS:
                print(f"error: {storage_error_message(args.exc_value)}", file=sys.stderr)
                return
            previous_hook(args)

        threading.excepthook = storage_fault_in_thread
        try:
            return fn(*args, **kwargs)
        except ShapeCorrError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_INVALID_INPUT)
        except KeyboardInterrupt:
            print("interrupted: what was completed is kept (cache entries and results are written atomically); "
                  "run the same command again to continue", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)
        except OSError as err:
            if err.errno not in STORAGE_ERRNOS:
                raise
            print(f"error: {storage_error_message(err)}", file=sys.stderr)
            sys.exit(EXIT_INVALID_INPUT)
        finally:
            threading.excepthook = previous_hook

    return wrapper  # type: ignore[return-value]


def user_config_error(err: Exception) -> ShapeCorrError:
    """Wrap an OmegaConf/Hydra config error (missing mandatory value, bad interpolation) as a ConfigError."""
    from shapecorr.errors import ConfigError

    return ConfigError(f"invalid configuration: {err}")


#: ``errno`` values of an ``OSError`` that are storage faults of the user's environment, not bugs: disk full or
#: over quota, no permission, read-only file system, a file where a folder is expected (or the reverse).
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.EEXIST,
                            errno.ENOTDIR, errno.EISDIR})


def storage_error_message(err: OSError) -> str:
    """One line for a storage fault: the file, the fault, and that finished work is kept."""
    where = f"{err.filename}: " if err.filename else ""
    fix = "free space" if err.errno in (errno.ENOSPC, errno.EDQUOT) else "make it writable"
    return (f"{where}{err.strerror or err} [errno {err.errno}]; finished results are kept (every file is written "
            f"atomically): {fix} or choose another output folder, then continue (evaluate.py: the same command and "
            "output_dir; train.py: ckpt_path=<run folder>/checkpoints/last.ckpt)")


def check_output_dir(path: str | Path, option: str) -> Path:
    """Create the output folder ``path`` (with its parents) and make sure a file can be written in it.

    Raises
    ------
    ConfigError
        ``path`` (or a parent) is a file, cannot be created, or is not writable; the message names the folder,
        the fault and ``option`` (the setting that chooses the folder).
    """
    from shapecorr.errors import ConfigError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"is a file, not a folder; choose another {option}", path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        raise ConfigError(f"cannot write the output folder here ({err.strerror or err}"
                          f"{f': {err.filename}' if err.filename and str(err.filename) != str(path) else ''}); "
                          f"choose another {option}", path) from None
    return path


class OutputDirCheck(Callback):
    """Hydra callback: before Hydra creates the run folder (``hydra.run.dir``), check it can be written.

    Registered in ``configs/hydra/default.yaml``. Hydra itself would stop with a traceback (``FileExistsError``,
    ``PermissionError``); this prints ``error: <folder>: ...`` naming the options that choose it and exits 2. The
    folder's parent is created and probed (the folder itself is named by the time, which Hydra resolves again).
    """

    def on_run_start(self, config, **kwargs) -> None:
        """Check the parent of ``hydra.run.dir`` (and the folder itself when it exists)."""
        from shapecorr.errors import ShapeCorrError

        run_dir = Path(str(config.hydra.run.dir))
        option = "hydra.run.dir=DIR (or paths.log_dir=DIR), or run from a writable folder"
        try:
            if run_dir.exists() and not run_dir.is_dir():
                check_output_dir(run_dir, option)
            check_output_dir(run_dir if run_dir.is_dir() else run_dir.parent, option)
        except ShapeCorrError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_INVALID_INPUT)
