"""What a system run leaves, whatever the backend that ran it."""

from dataclasses import dataclass, field


__all__ = ["SystemResult"]


@dataclass
class SystemResult:
    """What a system run leaves: the card, the LEDs at the end, the simulated and
    wall-clock seconds, and the models' protocol findings."""
    image: object
    led: int = 0
    seconds: float = 0.0
    wall_seconds: float = 0.0
    sdram_errors: list = field(default_factory=list)
    card_errors: list = field(default_factory=list)
    #: The front end's frame counters at the end, ``{channel: {counter: n}}`` (None where
    #: the backend does not read them).
    counters: dict | None = None
    #: The backend that ran, and its own figures (commands, blocks, accesses).
    backend: str | None = None
    stats: dict = field(default_factory=dict)
    #: What the backend could not model of the scenario.
    notes: list = field(default_factory=list)
