"""Ctrl-C that no library can swallow.

Python turns SIGINT into KeyboardInterrupt in the main thread, wherever it is. When that
is inside a native library's callback (casadi's IPOPT calls back into Python), the
library may catch it as one more exception and carry on: IPOPT then returns
``NonIpopt_Exception_Thrown`` and the fit goes on as if nothing was asked. So the CLI's
handler also sets a flag that the code after such calls checks; and a child process
that died of SIGINT (Ctrl-C in a terminal reaches the whole process group) is an
interrupt, not a crash.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

_INTERRUPTED = threading.Event()


def _on_sigint(signum: int, frame: Any) -> None:
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def install() -> Any:
    """Handle SIGINT with the flag as well (main thread only) and return the handler it
    replaces, for :func:`restore`. A SIGINT ignored by the process's parent (a background
    job of a script) stays ignored, as in Python."""
    _INTERRUPTED.clear()
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)
        # Restart interrupted system calls (SA_RESTART) in native code on every thread
        # (a compiler's reads); Python's own waits still wake for the handler (PEP 475;
        # sem_wait and select are never restarted).
        signal.siginterrupt(signal.SIGINT, False)
    return previous


def restore(previous: Any) -> None:
    """Put back the handler :func:`install` replaced; a Ctrl-C it saw is forgotten (the
    verb it stopped has ended)."""
    _INTERRUPTED.clear()
    if previous is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, previous)


def ignore() -> None:
    """Ignore SIGINT from now on (main thread only): once a verb has finished, its exit
    code says what it did."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def raise_if_interrupted() -> None:
    """KeyboardInterrupt if SIGINT arrived, though a library swallowed its exception."""
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


def raise_if_child_interrupted(returncode: int | None) -> None:
    """KeyboardInterrupt if a child process ended by SIGINT."""
    if returncode == -signal.SIGINT:
        raise KeyboardInterrupt
