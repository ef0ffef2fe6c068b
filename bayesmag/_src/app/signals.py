"""Ctrl-C and SIGTERM for the command line: one line, exit status 130 / 143 within 2 s, the output folder safe.

Installed only by the console entry point (:func:`handling` in ``cli.main``), never on import:
a library caller's own signal handling is left alone. While installed:

* SIGINT / SIGTERM raise :class:`Interrupted` in the main thread. The ``finally`` blocks of the
  output machinery run as for any error: the staging folder is removed, the lock released, the
  figure process killed; ``main`` prints one line and the process exits with 128 + signal. From the
  signal on, that line is all the process prints on stderr: what other threads and libraries would
  print while stopping (a Dask scheduler's "Task exception was never retrieved") goes to /dev/null.
* A watchdog thread is woken by the signal itself (``signal.set_wakeup_fd``), also when the main
  thread is busy in compiled code or waits for training threads to finish their batch. If the
  process has not exited after ``grace`` seconds it runs the registered clean-ups
  (:func:`on_abort`: remove the staging folder, release the lock) and ends the process with
  ``os._exit``. The figure process notices its parent is gone and exits too.
* :func:`critical` marks the two-phase swap: a signal arriving inside it is acted on after it,
  and the watchdog waits for it, so a folder is never caught half-renamed.
* :func:`parent_decides` starts child processes (a Dask cluster's workers) that do not take the Ctrl-C a terminal
  sends to the whole process group, so they print no traceback of their own: the parent stops them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import threading
from typing import Callable

__all__ = ["Interrupted", "handling", "on_abort", "critical", "announce", "parent_decides"]

_NAMES = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}
_state = threading.local()
_lock = threading.RLock()             # held by the swap (critical) and by the watchdog while it cleans up
_cleanups: dict[int, Callable[[], None]] = {}
_said = threading.Event()             # the one line is printed once, by whoever gets there first
_active = False
_depth = 0
_pending: int | None = None
_fired: int | None = None
_stderr: int | None = None          # a copy of fd 2 once muted (:func:`_mute`): where the one line goes


class Interrupted(KeyboardInterrupt):
    """The command was stopped by a signal; ``code`` is the exit status (128 + signal number)."""

    def __init__(self, signum: int):
        super().__init__(_NAMES.get(signum, f"signal {signum}"))
        self.signum = signum
        self.code = 128 + signum


def on_abort(fn: Callable[[], None]) -> Callable[[], None]:
    """Register ``fn`` to run if the watchdog must end the process; returns a function that unregisters it."""
    key = id(fn)
    _cleanups[key] = fn
    return lambda: _cleanups.pop(key, None)


@contextlib.contextmanager
def critical():
    """A block no signal interrupts: a signal that arrives inside is raised right after it."""
    global _depth, _pending
    with _lock:
        _depth += 1
        try:
            yield
        finally:
            _depth -= 1
    if _depth == 0 and _pending is not None and threading.current_thread() is threading.main_thread():
        signum, _pending = _pending, None
        raise Interrupted(signum)


@contextlib.contextmanager
def parent_decides():
    """Processes started in the block, or later by threads started in it, never take SIGINT: the parent decides.

    A terminal's Ctrl-C goes to the whole foreground process group. SIGINT is blocked in this thread for the block: a
    thread started in it inherits the mask, and a child process keeps it through fork and exec (CPython's resource
    tracker relies on the same). So a Dask cluster's workers, started by its threads, print no ``KeyboardInterrupt``
    traceback; this process stops them as it unwinds. A SIGINT arriving meanwhile is not lost: a thread that does not
    block it takes it (the watchdog's), or this one when the block ends. Under :func:`handling` the multiprocessing
    resource tracker is started first and quietly: started inside, it would unblock SIGINT in the thread that starts it,
    and after an interrupt (the process ends by ``os._exit``) it reports the semaphores it then removes as leaked.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    if _active:
        _quiet_resource_tracker()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _quiet_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (if not running) with its leak warnings off (its ``-W`` flags come
    from ``sys.warnoptions``)."""
    from multiprocessing import resource_tracker
    flag = "ignore::UserWarning:multiprocessing.resource_tracker"
    added = flag not in sys.warnoptions
    if added:
        sys.warnoptions.append(flag)
    try:
        resource_tracker.ensure_running()
    finally:
        if added:
            sys.warnoptions.remove(flag)


def announce(signum: int) -> None:
    """Print the one line about the interrupt (once per process)."""
    if _said.is_set():
        return
    _said.set()
    line = f"bayesmag: interrupted by {_NAMES.get(signum, signum)}; stopped without leaving a partial result.\n"
    if _stderr is not None:
        with contextlib.suppress(OSError):
            os.write(_stderr, line.encode())
        return
    sys.stderr.write(line)
    sys.stderr.flush()


def _mute() -> None:
    """Send fd 2 to /dev/null, keeping a copy for :func:`announce`: after an interrupt the one line is all that is
    printed, whatever other threads (a cluster's teardown, a training thread) write while the process stops."""
    global _stderr
    if _stderr is not None:
        return
    with contextlib.suppress(OSError, ValueError):
        sys.stderr.flush()                  # what was written before the signal still shows
    try:
        saved = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        _stderr = saved
    except OSError:
        pass


def _unmute() -> None:
    global _stderr
    if _stderr is None:
        return
    with contextlib.suppress(OSError):
        os.dup2(_stderr, 2)
        os.close(_stderr)
    _stderr = None


def _handler(signum, frame):
    global _pending, _fired
    if _fired is not None:              # a second Ctrl-C while stopping: the watchdog finishes the job
        return
    _fired = signum
    _mute()
    if _depth > 0:
        _pending = signum
        return
    raise Interrupted(signum)


def _watch(sock: socket.socket, grace: float, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            data = sock.recv(1)
        except OSError:
            return
        if not data or stop.is_set():
            return
        signum = data[0]
        if signum not in _NAMES:
            continue
        if stop.wait(grace):            # the main thread finished in time
            return
        if not _lock.acquire(timeout=10):
            pass                        # a swap of renames cannot take 10 s; go on regardless
        announce(signum)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)         # nothing after the one line (a half-unwound main thread)
            os.dup2(devnull, 2)
        except OSError:
            pass
        for fn in list(_cleanups.values())[::-1]:
            with contextlib.suppress(BaseException):
                fn()
        os._exit(128 + signum)


def _quiet_hook(old):
    """An Interrupted raised inside a finaliser (``__del__``) is swallowed by Python: no "Exception ignored"
    traceback for it; the watchdog ends the process instead."""
    def hook(u):
        if isinstance(u.exc_value, Interrupted):
            return
        old(u)
    return hook


@contextlib.contextmanager
def handling(*, grace: float = 0.6):
    """Install the handlers and the watchdog for the block (main thread only), then restore the old ones."""
    global _active, _fired, _pending
    if threading.current_thread() is not threading.main_thread() or _active:
        yield
        return
    r, w = socket.socketpair()
    r.setblocking(True)
    w.setblocking(False)
    stop = threading.Event()
    old = {s: signal.getsignal(s) for s in _NAMES}
    old_fd = signal.set_wakeup_fd(w.fileno(), warn_on_full_buffer=False)
    old_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_hook(old_hook)
    for s in _NAMES:
        signal.signal(s, _handler)
    t = threading.Thread(target=_watch, args=(r, grace, stop), name="bayesmag-signal-watchdog", daemon=True)
    t.start()
    _active, _fired, _pending = True, None, None
    try:
        yield
    finally:
        stop.set()
        with contextlib.suppress(OSError):
            w.send(b"\0")             # wake the watchdog so that it sees stop
        for s, h in old.items():
            signal.signal(s, h)
        signal.set_wakeup_fd(old_fd)
        sys.unraisablehook = old_hook
        _unmute()
        w.close()
        r.close()
        _active = False
