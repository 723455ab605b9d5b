"""Independent jobs in forked processes, up to one per core at once, each result back through a pipe.

The staged collection trains its final models this way (`downwash.staged`): each model trains on
one thread from its own seed, so it is bit-identical to one trained in the calling process.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import sys
import traceback
from typing import Any, Callable, Iterator, Sequence

__all__ = ["in_parallel"]


def in_parallel(fn: Callable[[str], dict], items: Sequence[str]) -> Iterator[tuple[str, dict]]:
    """(item, fn(item)) for every item, as each finishes, up to one forked process per core at once.

    For independent trainings: each trains on one thread (`TrainConfig.num_threads`) from its
    own seed, so a model is bit-identical to one trained in this process (a test checks), and
    two cores train two at once. fn must write its own outputs (atomically); its result (small,
    picklable) comes back through a pipe. Not on Linux (fork is unsafe on macOS, absent on Windows),
    with one core, or inside a daemonic process: one after another, in this process.
    """
    workers = min(len(items), os.cpu_count() or 1)
    # fork is the only start method without re-imports; a daemonic process may not have children
    if workers < 2 or not sys.platform.startswith("linux") or multiprocessing.current_process().daemon:
        for item in items:
            yield item, fn(item)
        return
    ctx = multiprocessing.get_context("fork")
    todo, running = list(items), {}
    try:
        while todo or running:
            while todo and len(running) < workers:
                item = todo.pop(0)
                receive, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_run_child, args=(fn, item, send), daemon=True)
                proc.start()
                send.close()
                running[receive] = (item, proc)
            for receive in multiprocessing.connection.wait(list(running)):
                item, proc = running.pop(receive)
                try:
                    ok, value = receive.recv()
                except EOFError:
                    ok, value = False, "the process ended without a result"
                proc.join()
                if not ok and proc.exitcode:
                    value = f"{value} (exit code {proc.exitcode})"
                if not ok:
                    raise RuntimeError(f"{item}: {value}")
                yield item, value
    finally:
        for _, proc in running.values():
            proc.kill()


def _run_child(fn: Callable[[str], dict], item: str, send: Any) -> None:
    try:
        send.send((True, fn(item)))
    except BaseException:  # the parent raises it, with the child's traceback
        send.send((False, traceback.format_exc()))
