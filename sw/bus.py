"""The firmware's view of the hardware: asynchronous register access and block data.

Firmware is written once against these interfaces. Backends implement them: the Amaranth
simulator (:mod:`maglog.sim.backends.amaranth`), cocotb
(:mod:`maglog.sim.backends.cocotb_sdio`) and the transaction-level model of the logger
(:mod:`maglog.sim.models.logger`).

Two exceptions end the firmware from outside; they derive from :class:`BaseException` so
that no ``except Exception`` in the firmware catches them.
"""

import abc


__all__ = ["RegisterBus", "BlockPort", "BusTimeout", "HardwareReset", "PowerCut"]


class BusTimeout(Exception):
    """A condition did not come true in time."""


class HardwareReset(BaseException):
    """The hardware reset the CPU (a watchdog expiry).

    Raised by a backend's :class:`RegisterBus` from the first access after the reset.
    Firmware never catches it: the harness restarts the application from the top, as a
    processor boots again after its reset."""


class PowerCut(BaseException):
    """The simulated power was cut.

    Raised by a backend's :class:`RegisterBus`; the run ends there, and the card image is
    what the card holds at that instant."""


class RegisterBus(abc.ABC):
    """Word-addressed 32-bit register access, and time."""

    @abc.abstractmethod
    async def read(self, address):
        """The word at ``address``."""

    @abc.abstractmethod
    async def write(self, address, value):
        """Write ``value`` to ``address``."""

    @abc.abstractmethod
    async def wait(self, seconds):
        """Let ``seconds`` of (simulated) time pass."""

    @abc.abstractmethod
    def now(self):
        """Seconds since the firmware started."""

    async def wait_event(self, address, predicate, *, timeout, poll=1e-6, what="condition"):
        """Read ``address`` until ``predicate(word)`` holds; return that word.

        Raises :class:`BusTimeout` after ``timeout`` seconds."""
        deadline = self.now() + timeout
        while True:
            word = await self.read(address)
            if predicate(word):
                return word
            if self.now() >= deadline:
                raise BusTimeout(f"{what} not reached within {timeout} s")
            await self.wait(poll)


class BlockPort(abc.ABC):
    """Where block data comes from and goes to (the DMA's side of the SD host)."""

    @abc.abstractmethod
    async def send(self, data):
        """Queue ``data`` (whole blocks) for the host's write stream."""

    @abc.abstractmethod
    async def discard(self):
        """Drop queued write data that the host did not take (after a failed write)."""

    @abc.abstractmethod
    async def receive(self, count):
        """The next ``count`` bytes of the host's read stream."""
