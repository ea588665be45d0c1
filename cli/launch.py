"""The ``psonurbs`` console script: the command line, stoppable while it loads.

Loading the command line (numpy, scipy and the fitting's modules) takes most of a
second. A Ctrl-C or SIGTERM in that time ends the command as one in the middle of a fit
does, with one line on stderr and its exit code (130 interrupted, 143 terminated),
instead of Python's traceback of the import it cut short. Nothing has been read or
written by then. A signal the shell started the command with ignored (a background job)
stays ignored.
"""
from __future__ import annotations

import signal
import sys

STOPS = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated")}


def _stop_while_loading(signum: int, frame) -> None:
    code, word = STOPS[signum]
    sys.stderr.write(f"psonurbs: {word}\n")
    raise SystemExit(code)


def stop_while_loading() -> None:
    """Ctrl-C and SIGTERM end the process quietly until the command line handles them."""
    for signum in STOPS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _stop_while_loading)


def main() -> None:
    stop_while_loading()
    from psonurbs.cli.main import main as command_line

    if signal.getsignal(signal.SIGINT) is _stop_while_loading:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # KeyboardInterrupt: the command's own handling
    command_line()  # (it sets SIGTERM's)
