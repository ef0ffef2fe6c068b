"""Where a job's figures are drawn: in this process (library calls), or in one worker process (command line).

:class:`FigureWorker` starts a plain ``python -c`` child (no ``multiprocessing``: nothing re-imports
the user's ``__main__``, no resource tracker). Tasks go to it as pickles over its stdin, answers come
back over its stdout; its stderr goes to a private temporary file (never the caller's terminal or
pipe). A reader thread in the child watches stdin: when the parent dies, however it dies (SIGKILL
included), the pipe closes and the child exits at once. :class:`InlineFigures` has the same
interface and draws in the calling process at :meth:`~InlineFigures.finish`.

Example::

    with FigureWorker() as figs:          # or InlineFigures()
        figs.warm()
        figs.submit(physics_figures, test, columns)    # called as physics_figures(folder, test, columns)
        ...                                            # the computation goes on meanwhile
        figs.finish(staging)                           # the PNGs land in staging
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

__all__ = ["FigureWorker", "InlineFigures", "figures"]

# The child: self-contained (it imports nothing of bayesmag until the first task names a function).
# Message 1 is the parent's sys.path; then (seq, draw, args, kwargs) tuples; None asks it to quit.
_SERVER = r"""
import os, pickle, queue, signal, sys, threading, traceback
signal.signal(signal.SIGINT, signal.SIG_IGN)        # Ctrl-C reaches the whole group: the parent decides
inp, out = sys.stdin.buffer, sys.stdout.buffer
sys.stdout = sys.stderr                             # stray prints never corrupt the answers
sys.path[:] = pickle.load(inp)
tasks = queue.Queue()
def read():
    while True:
        try:
            msg = pickle.load(inp)
        except BaseException:                        # EOF: the parent is gone (or hung up): exit now
            os._exit(0)
        tasks.put(msg)
        if msg is None:
            return
threading.Thread(target=read, daemon=True).start()
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot                            # warm: the slow import happens while the parent computes
while True:
    msg = tasks.get()
    if msg is None:
        break
    seq, draw, args, kwargs = msg
    try:
        draw(*args, **kwargs)
        reply = (seq, None)
    except BaseException as e:
        reply = (seq, (type(e).__name__, str(e), traceback.format_exc()))
    pickle.dump(reply, out)
    out.flush()
"""


class FigureWorker:
    """Draws figures in one child process while this one goes on; :meth:`finish` waits, re-raises the
    first drawing error and moves the files into the output folder.

    A process, not a thread: matplotlib is pure Python and would hold the GIL against the main
    thread's tracing. ``draw`` must be a module-level function of an importable module (never
    ``__main__``) and its arguments picklable. Used only by the command line, and there only with
    ``BAYESMAG_FIGURE_WORKER=1`` (it did not pay on the 2-core machine: ``benchmarks/bench_figures.py``);
    library calls always draw in-process (:class:`InlineFigures`).
    """

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._proc: subprocess.Popen | None = None
        self._log = None
        self._tmp = Path(tempfile.mkdtemp(prefix="bayesmag-figures-")) if enabled else None
        self._pending: list[int] = []
        self._seq = 0

    def warm(self) -> None:
        """Start the process now (interpreter, matplotlib import) rather than at the first figure."""
        if self.enabled and self._proc is None:
            self._log = tempfile.TemporaryFile(prefix="bayesmag-figures-log-")
            env = {**os.environ, "MPLBACKEND": "Agg"}
            self._proc = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=self._log, env=env, close_fds=True)
            self._send(list(sys.path))

    @property
    def pid(self) -> int | None:
        """The worker's process id (None before :meth:`warm` or when disabled)."""
        return None if self._proc is None else self._proc.pid

    def _send(self, msg) -> None:
        try:
            pickle.dump(msg, self._proc.stdin)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise RuntimeError(f"the figure process died: {self._log_tail()}") from None

    def _log_tail(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        lines = self._log.read().decode(errors="replace").strip().splitlines()
        return lines[-1] if lines else f"exit status {self._proc.poll()}"

    def submit(self, draw: Callable[..., object], *args, **kwargs) -> None:
        """Queue ``draw(folder, *args, **kwargs)``; nothing when the worker is disabled."""
        if not self.enabled:
            return
        if getattr(draw, "__module__", "__main__") == "__main__":
            raise ValueError(f"{draw!r} lives in __main__; the figure process never imports the caller's script. "
                             f"Give a function of an importable module.")
        self.warm()
        self._seq += 1
        self._send((self._seq, draw, (self._tmp, *args), kwargs))
        self._pending.append(self._seq)

    def finish(self, out: Path) -> list[str]:
        """Wait for every queued figure, raise the first error, move the files into ``out``; their names."""
        if not self.enabled:
            return []
        first = None
        while self._pending:
            try:
                seq, err = pickle.load(self._proc.stdout)
            except (EOFError, pickle.UnpicklingError, OSError):
                self._pending = []
                raise RuntimeError(f"the figure process died: {self._log_tail()}") from None
            self._pending.remove(seq)
            if err is not None and first is None:
                first = err
        if first is not None:
            name, msg, tb = first
            raise RuntimeError(f"drawing a figure failed: {name}: {msg}\n{tb}")
        names = sorted(p.name for p in self._tmp.iterdir())
        for name in names:
            shutil.move(str(self._tmp / name), str(Path(out) / name))
        return names

    def close(self, *, kill: bool = False) -> None:
        """Stop the process (asked to quit, or killed on an error or interrupt), remove the private folder."""
        p, self._proc = self._proc, None
        if p is not None:
            if not kill:
                try:
                    pickle.dump(None, p.stdin)
                    p.stdin.close()
                    p.wait(timeout=10)
                except (OSError, ValueError, subprocess.TimeoutExpired):
                    kill = True
            if kill:
                p.kill()
                p.wait()
            for f in (p.stdin, p.stdout):
                try:
                    f.close()
                except OSError:
                    pass
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        self.enabled = False

    def __enter__(self) -> "FigureWorker":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(kill=exc_type is not None)


class InlineFigures:
    """:class:`FigureWorker`'s interface, drawing in this process at :meth:`finish` (nothing is spawned)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._tasks: list = []
        self.pid = None

    def warm(self) -> None:
        """Nothing to start."""

    def submit(self, draw: Callable[..., object], *args, **kwargs) -> None:
        """Queue ``draw(folder, *args, **kwargs)``; nothing when disabled."""
        if self.enabled:
            self._tasks.append((draw, args, kwargs))

    def finish(self, out: Path) -> list[str]:
        """Draw every queued figure into ``out``; the names of the files that appeared."""
        out = Path(out)
        before = set(os.listdir(out)) if self._tasks else set()
        for draw, args, kwargs in self._tasks:
            draw(out, *args, **kwargs)
        names = sorted(set(os.listdir(out)) - before) if self._tasks else []
        self._tasks = []
        return names

    def close(self, **_) -> None:
        self._tasks = []

    def __enter__(self) -> "InlineFigures":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def figures(enabled: bool, *, worker: bool) -> FigureWorker | InlineFigures:
    """A figure drawer: the worker process (``worker``, command line) or this process (library calls)."""
    return FigureWorker(enabled) if worker else InlineFigures(enabled)
