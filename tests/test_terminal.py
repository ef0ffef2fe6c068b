"""app/terminal.py: progress bars only where someone watches (issue 26 item 18)."""

import io
import sys
import types

import pytest

from bayesmag._src.app.terminal import interactive_output


class _Tty(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("stream, want", [(io.StringIO(), False), (_Tty(), True), (object(), False)])
def test_a_terminal_is_watched_a_file_or_pipe_is_not(stream, want, monkeypatch):
    monkeypatch.delitem(sys.modules, "IPython", raising=False)
    assert interactive_output(stream) is want


def test_a_closed_stream_is_not_watched(monkeypatch):
    monkeypatch.delitem(sys.modules, "IPython", raising=False)
    s = io.StringIO()
    s.close()
    assert interactive_output(s) is False


@pytest.mark.parametrize("shell, want", [("ZMQInteractiveShell", True), ("TerminalInteractiveShell", False),
                                         (None, False)])
def test_a_jupyter_kernel_is_watched(shell, want, monkeypatch):
    fake = types.ModuleType("IPython")
    fake.get_ipython = (lambda: type(shell, (), {})()) if shell else (lambda: None)
    monkeypatch.setitem(sys.modules, "IPython", fake)
    assert interactive_output(io.StringIO()) is want              # widgets in a notebook; not a plain IPython pipe
