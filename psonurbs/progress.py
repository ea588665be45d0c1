"""Where a long fit is, for whoever shows progress: the stage it reports.

A fit to a tolerance tries many nets, a whole object fits many regions and then joins
them; the swarm's iterations (``on_iteration``) say how far one fit is, not which. Each
such step reports a stage: a sentence and the number of swarm iterations its fit will
call ``on_iteration`` with (1 for a fit without a swarm, None when it runs no fit)::

    with progress.reporting(lambda text, iterations: print(text, iterations)):
        fit_points(points, config)   # "searched net 4: 9x13, uniform knots", 1

Stages nest: within ``progress.within("face 2 of 3")`` every stage reported reads "face 2
of 3: ...". Nothing is reported without a receiver (the default), and a thread or process
of its own starts without one: the fits of workers and of a cluster report nothing.
"""
from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator

Receiver = Callable[[str, "int | None"], None]  # (the stage's sentence, its fit's swarm iterations)

_receiver: ContextVar[Receiver | None] = ContextVar("psonurbs_progress", default=None)


def stage(text: str, iterations: int | None = None) -> None:
    """Report a stage to the receiver in force, if any."""
    receiver = _receiver.get()
    if receiver is not None:
        receiver(text, iterations)


@contextmanager
def reporting(receiver: Receiver | None) -> Iterator[None]:
    """Stages reported inside go to ``receiver`` (None: nowhere)."""
    token = _receiver.set(receiver)
    try:
        yield
    finally:
        _receiver.reset(token)


@contextmanager
def within(prefix: str, iterations: int | None = None) -> Iterator[None]:
    """A stage of its own (``prefix``, reported on entry), whose inner stages read
    "PREFIX: ..."."""
    outer = _receiver.get()
    if outer is None:
        yield
        return
    outer(prefix, iterations)
    with reporting(lambda text, inner: outer(f"{prefix}: {text}", inner)):
        yield
