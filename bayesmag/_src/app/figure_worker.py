"""Where a job's figures are drawn: in this process (library calls), or shared with one worker process
(command line).

:class:`FigureWorker` starts a plain ``python -c`` child (no ``multiprocessing``: nothing re-imports
the user's ``__main__``, no resource tracker). Tasks go to it as pickles over its stdin, one at a
time, from a feeder thread of this process; answers come back over its stdout; its stderr goes to a
private temporary file (never the caller's terminal or pipe). A reader thread in the child watches
stdin: when the parent dies, however it dies (SIGKILL included), the pipe closes and the child exits
at once. At :meth:`~FigureWorker.finish` this process draws the tasks the worker has not taken yet
(``share=True``), so that two cores draw. :class:`InlineFigures` has the same interface and draws in
the calling process at :meth:`~InlineFigures.finish`.

Example::

    with FigureWorker(preload=["bayesmag._src.app.plots"]) as figs:     # or InlineFigures()
        figs.warm()                                    # interpreter, matplotlib, preload: while we compute
        figs.submit(draw, name, data)                  # called as draw(folder, name, data)
        ...                                            # the computation goes on meanwhile
        figs.finish(staging)                           # the PNGs land in staging
"""

from __future__ import annotations

import collections
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Callable

__all__ = ["FigureWorker", "InlineFigures", "figures", "JOB_MODULES", "JOB_BARE"]

#: What a job's figure process imports at start, while the job computes (the drawing functions of its tasks).
JOB_MODULES = ("bayesmag._src.app.plots", "bayesmag._src.app.hybrid_plots", "bayesmag._src.app.network_plots")
#: The package the job's figure process enters bare (no ``__init__``: no JAX; see :class:`FigureWorker`).
JOB_BARE = {"bayesmag": str(Path(__file__).resolve().parents[2])}

# The child: self-contained (it imports nothing of bayesmag but the modules the parent names to preload).
# Message 1 is the parent's sys.path, message 2 the modules to import at start; then (seq, draw, args, kwargs)
# tuples; None asks it to quit.
_SERVER = r"""
import importlib, os, pickle, queue, signal, sys, threading, traceback
signal.signal(signal.SIGINT, signal.SIG_IGN)        # Ctrl-C reaches the whole group: the parent decides
inp, out = sys.stdin.buffer, sys.stdout.buffer
sys.stdout = sys.stderr                             # stray prints never corrupt the answers
sys.path[:] = pickle.load(inp)
preload, bare = pickle.load(inp)
import types
for name, path in bare.items():                     # a package entered without running its __init__
    pkg = types.ModuleType(name)
    pkg.__path__ = [path]
    sys.modules[name] = pkg
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
import matplotlib.pyplot                            # warm: the slow imports happen while the parent computes
for name in preload:
    try:
        importlib.import_module(name)
    except Exception:                               # the task that needs it reports the error
        pass
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
    """Draws figures in one child process while this one goes on; :meth:`finish` draws what the child
    has not taken yet here (``share``), waits, re-raises the first drawing error and moves the files
    into the output folder.

    A process, not a thread: matplotlib is pure Python and would hold the GIL against the main
    thread. ``draw`` must be a module-level function of an importable module (never ``__main__``)
    and its arguments picklable (plain arrays: the child never needs JAX). The child gets one task at
    a time (a feeder thread here sends the next when it answers), so that the two processes share
    the queue. Used only by the command line (``BAYESMAG_FIGURE_WORKER=0`` turns it off); library
    calls always draw in-process (:class:`InlineFigures`). ``preload``: modules the child imports at
    start (:meth:`warm`), while this process computes. ``bare``: ``{package: folder}`` entered in the child
    without running the package's ``__init__`` (:data:`JOB_BARE`: ``bayesmag``'s imports JAX and switches
    it to float64, which a process that only draws never needs: ~1 CPU-s less to start).
    """

    def __init__(self, enabled: bool = True, preload: tuple[str, ...] | list[str] = (),
                 bare: dict[str, str] | None = None):
        self.enabled = enabled
        self.preload = list(preload)
        self.bare = dict(bare or {})
        self._proc: subprocess.Popen | None = None
        self._log = None
        self._tmp = Path(tempfile.mkdtemp(prefix="bayesmag-figures-")) if enabled else None
        self._queue: collections.deque = collections.deque()    # submitted, not yet taken by either process
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._feeder: threading.Thread | None = None
        self._busy = False                  # a task is at the child
        self._stop = False
        self._errors: list = []             # (name, message, traceback) of failed tasks
        self._died: str | None = None       # why the child stopped answering
        self._seq = 0

    def warm(self) -> None:
        """Start the process now (interpreter, matplotlib, ``preload``) rather than at the first figure."""
        if self.enabled and self._proc is None:
            self._log = tempfile.TemporaryFile(prefix="bayesmag-figures-log-")
            env = {**os.environ, "MPLBACKEND": "Agg"}
            self._proc = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=self._log, env=env, close_fds=True)
            self._send(list(sys.path))
            self._send((self.preload, self.bare))
            self._feeder = threading.Thread(target=self._feed, name="bayesmag-figures", daemon=True)
            self._feeder.start()

    @property
    def pid(self) -> int | None:
        """The worker's process id (None before :meth:`warm` or when disabled)."""
        return None if self._proc is None else self._proc.pid

    def _send(self, msg, proc: subprocess.Popen | None = None) -> None:
        proc = proc or self._proc
        try:
            pickle.dump(msg, proc.stdin)
            proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError, AttributeError):
            raise RuntimeError(f"the figure process died: {self._log_tail()}") from None

    def _log_tail(self) -> str:
        log, proc = self._log, self._proc
        try:
            log.seek(0)
            lines = log.read().decode(errors="replace").strip().splitlines()
        except (AttributeError, ValueError, OSError):     # closed meanwhile (close() after a kill)
            return ""
        return lines[-1] if lines else f"exit status {proc.poll() if proc else None}"

    def _feed(self) -> None:
        """Feeder thread: hand the child the next queued task whenever it is idle, collect its answer."""
        proc = self._proc
        while True:
            with self._wake:
                while not self._queue and not self._stop:
                    self._wake.wait()
                if self._stop:
                    return
                task = self._queue.popleft()
                self._busy = True
            try:
                self._seq += 1
                draw, args, kwargs = task
                self._send((self._seq, draw, (self._tmp, *args), kwargs), proc)
                _, err = pickle.load(proc.stdout)
            except (RuntimeError, EOFError, pickle.UnpicklingError, OSError, ValueError):
                with self._wake:
                    self._died = f"the figure process died: {self._log_tail()}"
                    self._busy = False
                    self._wake.notify_all()
                return
            with self._wake:
                if err is not None:
                    self._errors.append(err)
                self._busy = False
                self._wake.notify_all()

    def submit(self, draw: Callable[..., object], *args, **kwargs) -> None:
        """Queue ``draw(folder, *args, **kwargs)``; nothing when the worker is disabled."""
        if not self.enabled:
            return
        if getattr(draw, "__module__", "__main__") == "__main__":
            raise ValueError(f"{draw!r} lives in __main__; the figure process never imports the caller's script. "
                             f"Give a function of an importable module.")
        self.warm()
        with self._wake:
            self._queue.append((draw, args, kwargs))
            self._wake.notify_all()

    def finish(self, out: Path, *, share: bool = True) -> list[str]:
        """Draw the tasks the child has not taken yet here (``share``), wait for the child, raise the first
        error, move its files into ``out``; the names of every file drawn, sorted."""
        if not self.enabled:
            return []
        out = Path(out)
        here: list[str] = []
        while share:
            with self._wake:
                if not self._queue:
                    break
                draw, args, kwargs = self._queue.popleft()
            try:
                before = set(os.listdir(out))
                draw(out, *args, **kwargs)
                here += sorted(set(os.listdir(out)) - before)
            except Exception as e:
                import traceback
                with self._wake:
                    self._errors.append((type(e).__name__, str(e), traceback.format_exc()))
        with self._wake:
            while (self._queue or self._busy) and self._died is None:
                self._wake.wait()
            died, errors = self._died, list(self._errors)
            self._queue.clear()
            self._errors = []
        if died is not None:
            raise RuntimeError(died)
        if errors:
            name, msg, tb = errors[0]
            raise RuntimeError(f"drawing a figure failed: {name}: {msg}\n{tb}")
        names = sorted(p.name for p in self._tmp.iterdir())
        for name in names:
            shutil.move(str(self._tmp / name), str(out / name))
        return sorted(names + here)

    def close(self, *, kill: bool = False) -> None:
        """Stop the process (asked to quit, or killed on an error or interrupt), remove the private folder."""
        with self._wake:
            self._stop = True
            self._queue.clear()
            self._wake.notify_all()
        p, self._proc = self._proc, None
        if p is not None:
            if not kill:
                if self._feeder is not None:         # it ends after the task in flight, if any
                    self._feeder.join(timeout=10)
                try:
                    pickle.dump(None, p.stdin)
                    p.stdin.close()
                    p.wait(timeout=10)
                except (OSError, ValueError, subprocess.TimeoutExpired):
                    kill = True
            if kill:
                p.kill()
                p.wait()
                if self._feeder is not None:         # its read fails at once now
                    self._feeder.join(timeout=2)
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

    def finish(self, out: Path, *, share: bool = True) -> list[str]:
        """Draw every queued figure into ``out``; the names of the files that appeared (``share``: ignored)."""
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


def figures(enabled: bool, *, worker: bool, preload: tuple[str, ...] = (),
            bare: dict[str, str] | None = None) -> FigureWorker | InlineFigures:
    """A figure drawer: shared with a worker process (``worker``, command line) or this process (library calls)."""
    return FigureWorker(enabled, preload, bare) if worker else InlineFigures(enabled)
