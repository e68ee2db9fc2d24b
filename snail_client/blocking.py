"""The blocking face of the secure runner: ``SecureRunner`` runs ``AsyncSecureRunner`` on
its own (uvloop) event loop, for callers that are not asyncio programs (the CLI, the
``Localizer`` API, the benchmarks)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np

from snail_common.net.conn import new_event_loop
from snail_common.net.linkrates import AUTO

from .audit import DEFAULT_AUDIT_RATE, Audits
from .links import DEFAULT_LINK_TIMEOUT
from .secure import DEFAULT_AHEAD, DEFAULT_BUSY_WAIT, DEFAULT_TIMEOUT, AsyncSecureRunner
from .sessions import Address, FixedInputs, Invocation


class _CtrlC:
    """SIGINT as a flag and a cancelled task while the runner's loop runs, instead of a
    KeyboardInterrupt raised inside whichever callback runs (uvloop delivers signals
    there: a protocol took it for a lost connection, or the loop carried on). The flag is
    set in the handler itself, so a signal that comes as the loop stops is not lost. Armed
    only where Python itself turns SIGINT into KeyboardInterrupt (the main thread, SIGINT
    not ignored or taken by the caller), so nothing else's handling changes."""

    def __init__(self, loop: asyncio.AbstractEventLoop, task: asyncio.Task) -> None:
        self.seen = False
        self._loop, self._task = loop, task
        self._armed = (threading.current_thread() is threading.main_thread()
                       and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
        if self._armed:
            signal.signal(signal.SIGINT, self._on_signal)

    def _on_signal(self, *_: object) -> None:
        self.seen = True
        self._loop.call_soon_threadsafe(self._task.cancel)

    def disarm(self) -> None:
        if self._armed:
            signal.signal(signal.SIGINT, signal.default_int_handler)


class SecureRunner:
    """Blocking wrapper of AsyncSecureRunner with its own event loop (uvloop)."""

    def __init__(self, garbler_addr: Address, evaluator_addr: Address,
                 tls_dir: str | Path, timeout: float = DEFAULT_TIMEOUT,
                 connect_timeout: float = 10.0, ahead: int = DEFAULT_AHEAD,
                 busy_wait: float = DEFAULT_BUSY_WAIT, cert_name: str = "client",
                 link_timeout: float = DEFAULT_LINK_TIMEOUT,
                 scheme: str = AUTO, audit_rate: float = DEFAULT_AUDIT_RATE,
                 evidence_dir: str | Path | None = None) -> None:
        self._loop = new_event_loop()
        audits = Audits(audit_rate, Path(evidence_dir) if evidence_dir else None)
        self._runner = AsyncSecureRunner(garbler_addr, evaluator_addr, tls_dir, timeout,
                                         connect_timeout, ahead, busy_wait, cert_name,
                                         link_timeout, scheme, audits)

    def use_frame(self, handle: bytes, map_owner: str, relay: str | None = None) -> None:
        """Map-owner circuits take this frame's map-owner inputs (see the async runner)."""
        self._runner.use_frame(handle, map_owner, relay)

    def expect(self, circuit_id: str, count: int, fixed: FixedInputs | None = None) -> None:
        """At least ``count`` invocations of ``circuit_id`` are coming, sharing the
        ``fixed`` input bits (see the async runner); their garbling starts now."""
        async def announce() -> None:
            self._runner.expect(circuit_id, count, fixed)
            await asyncio.sleep(0)

        self._complete(announce())

    def fixed(self, circuit_id: str) -> FixedInputs | None:
        """The input bits ``expect`` last declared shared by ``circuit_id``'s runs."""
        return self._runner.fixed(circuit_id)

    def _complete(self, coro: Any) -> Any:
        """Run ``coro`` on this runner's loop. Ctrl-C cancels it through the loop (as
        ``asyncio.run`` does) rather than raising inside whichever callback it lands in,
        where a protocol took it for a lost connection or the loop carried on; the tasks it
        left are cancelled and finished, then KeyboardInterrupt is raised here."""
        task = self._loop.create_task(coro)
        ctrl_c = _CtrlC(self._loop, task)
        try:
            result = self._loop.run_until_complete(task)
        except (KeyboardInterrupt, SystemExit):  # the runner is going: settle its tasks
            self._settle()
            raise
        except BaseException:
            if not ctrl_c.seen:
                raise
        finally:
            ctrl_c.disarm()
        if ctrl_c.seen:
            self._settle()
            raise KeyboardInterrupt
        return result

    def _settle(self) -> None:
        pending = [t for t in asyncio.all_tasks(self._loop) if not t.done()]
        for task in pending:
            task.cancel()
        if pending:
            with contextlib.suppress(BaseException):
                self._loop.run_until_complete(asyncio.gather(*pending,
                                                             return_exceptions=True))

    def run(self, circuit_id: str, input_bits: np.ndarray) -> np.ndarray:
        """Decoded output bits; traffic and time of the run in ``self.last``."""
        return self.invoke(circuit_id, input_bits).outputs

    def invoke(self, circuit_id: str, input_bits: np.ndarray,
               frame: bytes | None = None) -> Invocation:
        """One secure run; IntegrityFailure where a check failed, the evaluator's for the
        garbler's tables included (``Audits.named``)."""
        return self._complete(self.audits.named(self._runner.invoke(circuit_id, input_bits,
                                                                    frame)))

    def health(self, role: str) -> dict[str, Any]:
        return self._complete(self._runner.health(role))

    @property
    def audits(self) -> Audits:
        """The runner's audits: their rate, counts and the servers refused (audit.py)."""
        return self._runner.audits

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The runner's event loop (threaded.py runs it in a thread of its own)."""
        return self._loop

    @property
    def async_runner(self) -> AsyncSecureRunner:
        """The asyncio runner this one wraps, for coroutines run on ``loop``."""
        return self._runner

    @property
    def scheme(self) -> str:
        """The garbling scheme of this runner's sessions."""
        return self._runner.scheme

    @property
    def endpoints(self) -> tuple[tuple[str, int], tuple[str, int], str | Path]:
        """(garbler address, evaluator address, TLS directory): to open more clients."""
        r = self._runner
        return r.garbler_addr, r.evaluator_addr, r.tls_dir

    @property
    def last(self) -> Invocation | None:
        return self._runner.last

    @property
    def totals(self) -> dict[str, int]:
        return self._runner.totals

    @property
    def invocations(self) -> int:
        return self._runner.invocations

    @property
    def retries(self) -> int:
        """Invocations run again on another replica after a retryable failure."""
        return self._runner.retries

    def close(self) -> None:
        if not self._loop.is_closed():
            with contextlib.suppress(Exception):
                self._loop.run_until_complete(self._runner.close())
            self._settle()
            self._loop.close()

    def __enter__(self) -> SecureRunner:
        self._complete(self._runner.connect())
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
