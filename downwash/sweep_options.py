"""A sweep's options, read and checked while the command lines parse: the grid from its text, the
Ray workers, the cells per task and the cluster's address (cheap to import: no torch, no Ray).

`grid_from_text` turns the command line's lists into a `downwash.sweep_cells.SweepGrid`;
`workers_problem` and `address_problem` say what a bad ``--workers`` or ``--address`` expects
(for the parsers' messages); `check_execution` and `check_address` raise ConfigError naming the
option, the latter also when nothing answers at the address within `ADDRESS_TIMEOUT` seconds
(before Ray, which would retry for minutes). `downwash.sweep` runs the sweep (and re-exports
everything here).
"""

from __future__ import annotations

import re
import socket
import threading
from typing import TYPE_CHECKING, Any, Callable

from downwash_core.errors import ConfigError

if TYPE_CHECKING:
    from downwash.sweep_cells import SweepGrid

__all__ = ["grid_from_text", "check_execution", "workers_problem", "address_problem", "check_address",
           "ADDRESS_TIMEOUT"]

ADDRESS_TIMEOUT = 3.0  # s: a running cluster answers at once; Ray itself would retry for minutes


def grid_from_text(fields: str, models: str, minutes: str, seeds: str, quick: bool = False) -> SweepGrid:
    """A grid from the command line's text: fields separated by ';' (a field spec holds commas),
    the rest by ','. ConfigError naming the option for an item that is not a number."""

    def items(name: str, text: str, convert: Callable[[str], Any], sep: str = ",") -> tuple:
        try:
            return tuple(convert(t.strip()) for t in text.split(sep) if t.strip())
        except ValueError:
            what = "numbers" if convert is float else "integers" if convert is int else "names"
            raise ConfigError(f"--{name}: expected a comma list of {what}, got {text!r}") from None

    from downwash.sweep_cells import SweepGrid

    specs = tuple(dict.fromkeys(t.strip() for t in fields.split(";"))) if fields.strip() else ("",)
    return SweepGrid(fields=specs, models=items("models", models, str), minutes=items("minutes", minutes, float),
                     seeds=items("seeds", seeds, int), quick=quick)


def check_execution(workers: int, batch: int, address: str = "") -> None:
    """ConfigError unless ``workers`` is 0 (all usable cores) or at most the usable cores
    (`workers_problem`), ``batch >= 1`` and ``address`` is well formed (`address_problem`)."""
    problem = workers_problem(workers)
    if problem:
        raise ConfigError(f"--workers: {problem}, got {workers!r}")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ConfigError(f"--batch: expected an integer >= 1 (cells per task), got {batch!r}")
    problem = address_problem(address)
    if problem:
        raise ConfigError(f"--address: {problem}, got {address!r}")


def workers_problem(workers: Any) -> str | None:
    """What ``workers`` (the CPUs of a local Ray) expects when it is bad, else None: 0 (all usable cores)
    or 1 up to the cores this process may use. More would start as many Ray workers, taking turns on
    the cores (the numbers do not change, only memory and time grow). Bounded with ``address`` too, where
    it is unused: one rule for every command line."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        return "expected an integer >= 0 (0: all usable cores)"
    if workers == 0:  # the default: no need to load the simulator (and MuJoCo) to count the cores
        return None
    from sim.physics import usable_cores

    cores = usable_cores()
    if workers > cores:
        return f"expected 0 (all usable cores) or 1..{cores} (the cores this machine lets the sweep use)"
    return None


_HOST = re.compile(r"[A-Za-z0-9]([A-Za-z0-9._-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\]")


def _split_address(address: str) -> tuple[str, int] | None:
    """(host, port) of HOST:PORT or ray://HOST:PORT (an IPv6 host in brackets), None when malformed."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not _HOST.fullmatch(host) or not re.fullmatch(r"[0-9]{1,5}", port) or not 1 <= int(port) <= 65535:
        return None
    return host.strip("[]"), int(port)


def address_problem(address: Any) -> str | None:
    """What ``address`` expects when it is malformed, else None: "" (a local Ray), "auto" (the cluster
    ``ray start`` runs on this machine), HOST:PORT of a running cluster's head (as ``ray start --head``
    prints it), or ray://HOST:PORT (its Ray Client server)."""
    if address in ("", "auto") or (isinstance(address, str) and _split_address(address)):
        return None
    return ("expected HOST:PORT of a running Ray cluster's head (port 1-65535, as ray start --head prints it), "
            "ray://HOST:PORT or auto")


def check_address(address: str, timeout: float = ADDRESS_TIMEOUT) -> None:
    """ConfigError naming ``address`` when it is malformed or nothing answers there within ``timeout``
    seconds (a TCP connection, the name lookup included), before Ray, which would retry for minutes.
    "" and "auto" pass ("auto" is looked up when Ray starts)."""
    problem = address_problem(address)
    if problem:
        raise ConfigError(f"--address: {problem}, got {address!r}")
    if address in ("", "auto"):
        return
    host, port = _split_address(address)
    outcome: list[BaseException | None] = []

    def connect() -> None:
        try:
            socket.create_connection((host, port), timeout=timeout).close()
            outcome.append(None)
        except OSError as e:
            outcome.append(e)

    # a thread: the timeout of create_connection does not cover the name lookup, which can hang
    probe = threading.Thread(target=connect, name="sweep-address-probe", daemon=True)
    probe.start()
    probe.join(timeout + 0.5)
    if outcome and outcome[0] is None:
        return
    why = ("no answer within {:g} s".format(timeout) if not outcome or isinstance(outcome[0], TimeoutError)
           else "unknown host" if isinstance(outcome[0], socket.gaierror)
           else "connection refused" if isinstance(outcome[0], ConnectionRefusedError)
           else outcome[0].strerror or type(outcome[0]).__name__)
    raise ConfigError(f"--address {address}: no Ray cluster answers there ({why}); start one with ray start "
                      "--head, or give its head's HOST:PORT")
