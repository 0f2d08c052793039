"""Reference frame filter, written from ``docs/frame-rules.md`` alone.

The gateware's ``FrameFilter`` judges each byte as it arrives. This model deliberately works
the other way round: it gathers a candidate frame as text (from a ``$`` up to the next ``$``,
LF or error-flagged byte) and then judges the whole candidate with string operations, finding
the earliest byte at which one of the rules of the rules page fires. Because every rule
depends only on the bytes up to the one it judges, "the earliest offending byte, ties
broken by rule number" is the same decision the byte-by-byte rules make.

The received stream is held as a ``str`` in which byte ``b`` is ``chr(b)`` and a byte with
the error flag is ``ERROR_MARK`` (a code point no byte can take), so a single regular
expression splits the stream into candidates. No frame FIFO is modelled: the ``overflow``
counter stays 0.
"""

from __future__ import annotations

import enum
import re
import string
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

__all__ = [
    "Kind",
    "FilterResult",
    "ReferenceFilter",
    "reference_filter",
    "COUNTER_NAMES",
    "DEFAULT_MAX_FRAME",
    "CESIUM_MAX_FRAME",
]


class Kind(enum.Enum):
    """The rule set of a channel."""

    NMEA = "nmea"
    PMAG = "pmag"
    CESIUM = "cesium"


KEPT = "kept"
CHECKSUM = "checksum"
NOT_WHITELISTED = "not_whitelisted"
OVERLONG = "overlong"
BAD_BYTE = "bad_byte"
UART_ERROR = "uart_error"
OVERFLOW = "overflow"
#: Counter names, in the order of the rules page.
COUNTER_NAMES = (KEPT, CHECKSUM, NOT_WHITELISTED, OVERLONG, BAD_BYTE, UART_ERROR, OVERFLOW)
COUNTER_WIDTH = 32
_COUNTER_MASK = (1 << COUNTER_WIDTH) - 1

#: MAX_FRAME build parameter default, for NMEA and ``$PMAG1``.
DEFAULT_MAX_FRAME = 128
#: Cesium frames are at most ``$`` + 15 body bytes + CR LF.
CESIUM_MAX_FRAME = 18
#: ``TTSSS,`` / ``PMAG1,`` and ``*hh``: the shortest body the checksum kinds accept.
MIN_CHECKED_BODY = 9
CESIUM_BODY = 15
BYTE_MAX = 0xFF

#: Stands for a received byte with the error flag (framing error, break, overrun).
ERROR_MARK = "\u0100"
_START = "$"
_CR = "\r"
_LF = "\n"
_FIELD_SEPARATOR = ","
_CHECKSUM_DELIMITER = "*"
_HEX_DIGITS = 2

# Rule numbers of the rules page, used to break ties at one byte.
_RULE_AFTER_CR = 3
_RULE_NOT_PRINTABLE = 4
_RULE_OVERLONG = 5
_RULE_POSITION = 8

#: A candidate frame: ``$``, then everything up to (not including) the next ``$``, LF or
#: error mark, which is captured by the look-ahead (absent when the stream ends first).
_CANDIDATE = re.compile(
    rf"\$(?P<content>[^$\n{ERROR_MARK}]*)(?=(?P<end>[$\n{ERROR_MARK}])?)"
)
#: Rule 4: inside a frame, anything but printable ASCII and CR (LF never reaches content).
_NOT_PRINTABLE = re.compile(r"[^\x20-\x7e\r]")
_CHECKSUM_TAIL = re.compile(rf"\*(?P<hex>[0-9A-Fa-f]{{{_HEX_DIGITS}}})\Z")
_FLUSH_QUALITY = re.compile(r"[1-9]")
_GGA = "GGA"
#: Positions 3-5 (the sentence name) as indices into the body, which starts at position 1.
_BODY_SENTENCE_NAME = slice(2, 5)
#: GGA fix quality: item 6 of the body up to its first ``*``, split at ``,``.
_GGA_QUALITY_ITEM = 6

_UPPER = frozenset(string.ascii_uppercase)
_DIGIT = frozenset(string.digits)


@dataclass(frozen=True)
class _HeaderRule:
    """Position check: ``templates[k][i]`` is the set allowed at position ``i + 1``.

    The frame drops at the first byte after which the header read so far is not a prefix of
    any template. With ``open_tail`` positions past the templates are free; otherwise any
    byte there (other than the line end) fails.
    """

    templates: tuple[tuple[frozenset[str], ...], ...]
    open_tail: bool

    def first_violation(self, head: str) -> int | None:
        """Frame position of the first failing byte of ``head`` (bytes from position 1)."""
        length = len(self.templates[0])
        checked = head[:length] if self.open_tail else head
        matched = max(_prefix_match(checked, template) for template in self.templates)
        return matched + 1 if matched < len(checked) else None


def _prefix_match(text: str, template: Sequence[frozenset[str]]) -> int:
    count = 0
    for char, allowed in zip(text, template):
        if char not in allowed:
            break
        count += 1
    return count


def _literal(text: str) -> tuple[frozenset[str], ...]:
    return tuple(frozenset(char) for char in text)


# Ref: docs/frame-rules.md "Kinds".
_HEADERS = {
    Kind.NMEA: _HeaderRule(
        templates=tuple(
            (_UPPER, _UPPER, *_literal(name + _FIELD_SEPARATOR)) for name in ("GGA", "ZDA", "VTG")
        ),
        open_tail=True,
    ),
    Kind.PMAG: _HeaderRule(templates=(_literal("PMAG1,"),), open_tail=True),
    Kind.CESIUM: _HeaderRule(
        templates=(
            (frozenset(" 1"), *[_DIGIT] * 5, *_literal("."), *[_DIGIT] * 3, *_literal(","), *[_DIGIT] * 4),
        ),
        open_tail=False,
    ),
}


@dataclass
class FilterResult:
    """What a filter kept, its counters and the indices of flushing GGA frames."""

    frames: list[bytes] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTER_NAMES, 0))
    #: Indices into ``frames`` of the kept GGA frames that raise the flush event.
    flushes: list[int] = field(default_factory=list)


def _event(item: object) -> tuple[int, bool]:
    if isinstance(item, int) and not isinstance(item, bool):
        byte, error = item, False
    elif hasattr(item, "data") and hasattr(item, "error"):
        byte, error = item.data, item.error  # RxEvent
    elif isinstance(item, (tuple, list)) and len(item) == 2:
        byte, error = item
    else:
        raise ValueError(f"Event must be a byte, an RxEvent or a (byte, error) pair, not {item!r}")
    if isinstance(byte, bool) or not isinstance(byte, int) or not 0 <= byte <= BYTE_MAX:
        raise ValueError(f"Byte must be an integer 0..{BYTE_MAX}, not {byte!r}")
    return byte, bool(error)


class ReferenceFilter:
    """Streaming reference filter: ``feed`` bytes, read ``result`` at any time.

    A frame still open when ``result`` is read is neither kept nor counted yet.
    """

    def __init__(self, kind: Kind | str, max_frame: int = DEFAULT_MAX_FRAME) -> None:
        self.kind = Kind(kind)
        if isinstance(max_frame, bool) or not isinstance(max_frame, int) or max_frame < 1:
            raise ValueError(f"Max frame length must be a positive integer, not {max_frame!r}")
        self.max_frame = CESIUM_MAX_FRAME if self.kind is Kind.CESIUM else max_frame
        self._header = _HEADERS[self.kind]
        self._pending: list[str] = []  # received since the last judged candidate
        self._result = FilterResult()
        self._taken = 0  # frames handed over by take_frames

    def feed(self, byte: int, error: bool = False) -> None:
        """One received byte and its error flag."""
        byte, error = _event((byte, error))
        self._pending.append(ERROR_MARK if error else chr(byte))

    def feed_all(self, events: bytes | Iterable[object]) -> None:
        """Bytes, or an iterable of bytes, ``RxEvent`` or ``(byte, error)`` pairs."""
        if isinstance(events, (bytes, bytearray, memoryview)):
            self._pending.append(bytes(events).decode("latin-1"))
            return
        for item in events:
            self.feed(*_event(item))

    @property
    def result(self) -> FilterResult:
        """Frames kept and counts so far (a copy)."""
        self._judge_pending()
        return FilterResult(
            frames=list(self._result.frames),
            counters=dict(self._result.counters),
            flushes=list(self._result.flushes),
        )

    def take_frames(self) -> list[bytes]:
        """The frames kept since the last call (or the start), in order, handed over: they
        are no longer held, so a long stream read this way keeps no frame history (what
        ``maglog record`` needs). ``result.frames`` then holds only frames not yet taken;
        counters count on, and ``result.flushes`` still numbers kept frames from the start.
        """
        self._judge_pending()
        frames, self._result.frames = self._result.frames, []
        self._taken += len(frames)
        return frames

    # --- judging --------------------------------------------------------------------------

    def _judge_pending(self) -> None:
        stream = "".join(self._pending)
        keep_from = len(stream)
        for candidate in _CANDIDATE.finditer(stream):
            content, end = candidate["content"], candidate["end"]
            outcome = self._judge(content, end)
            if outcome is None:  # still open at the end of what was received
                keep_from = candidate.start()
                break
            self._count(outcome, content)
        self._pending = [stream[keep_from:]] if keep_from < len(stream) else []

    def _judge(self, content: str, end: str | None) -> str | None:
        """The outcome of the frame ``$`` + ``content`` closed by ``end``; None if still open."""
        # Drops at a byte of the content: (frame position, rule number, cause); the earliest
        # byte decides, and at one byte the lowest rule number (the rules page's order).
        drops: list[tuple[int, int, str]] = []
        cr = content.find(_CR)
        if 0 <= cr < len(content) - 1:
            drops.append((cr + 2, _RULE_AFTER_CR, BAD_BYTE))
        if match := _NOT_PRINTABLE.search(content):
            drops.append((match.start() + 1, _RULE_NOT_PRINTABLE, BAD_BYTE))
        if 1 + len(content) > self.max_frame:
            drops.append((self.max_frame, _RULE_OVERLONG, OVERLONG))
        head = content if cr < 0 else content[:cr]  # a CR is never position-checked (rule 7)
        if (position := self._header.first_violation(head)) is not None:
            drops.append((position, _RULE_POSITION, NOT_WHITELISTED))
        if drops:
            return min(drops)[2]
        if end is None:
            return None
        if end == ERROR_MARK:
            return UART_ERROR  # rule 1
        if end == _START:
            return BAD_BYTE  # rule 2 (the "$" starts the next candidate)
        if 1 + len(content) + len(_LF) > self.max_frame:
            return OVERLONG  # rule 5 applies to the LF too
        return self._end_check(content.removesuffix(_CR))  # rule 6

    def _end_check(self, body: str) -> str:
        if self.kind is Kind.CESIUM:
            return KEPT if len(body) == CESIUM_BODY else NOT_WHITELISTED
        if len(body) < MIN_CHECKED_BODY:
            return NOT_WHITELISTED  # cut short
        tail = _CHECKSUM_TAIL.search(body)
        if tail is None:
            return CHECKSUM
        checksum = 0
        for char in body[: tail.start()]:
            checksum ^= ord(char)
        return KEPT if checksum == int(tail["hex"], 16) else CHECKSUM

    def _raises_flush(self, body: str) -> bool:
        if self.kind is not Kind.NMEA or body[_BODY_SENTENCE_NAME] != _GGA:
            return False
        fields = body.split(_CHECKSUM_DELIMITER, 1)[0].split(_FIELD_SEPARATOR)
        if len(fields) <= _GGA_QUALITY_ITEM:
            return False  # fewer fields: no event
        return _FLUSH_QUALITY.fullmatch(fields[_GGA_QUALITY_ITEM]) is not None

    def _count(self, outcome: str, content: str) -> None:
        counters = self._result.counters
        counters[outcome] = (counters[outcome] + 1) & _COUNTER_MASK
        if outcome != KEPT:
            return
        if self._raises_flush(content.removesuffix(_CR)):
            self._result.flushes.append(self._taken + len(self._result.frames))
        self._result.frames.append((_START + content + _LF).encode("ascii"))


def reference_filter(
    kind: Kind | str,
    events: bytes | Iterable[object],
    *,
    max_frame: int = DEFAULT_MAX_FRAME,
) -> FilterResult:
    """Run the reference filter of ``kind`` over ``events``.

    ``events`` is ``bytes`` or an iterable of ``int`` bytes, ``RxEvent`` or ``(byte, error)``
    pairs. ``max_frame`` is the MAX_FRAME build parameter (NMEA and ``$PMAG1``; cesium frames
    are always at most 18 bytes). A frame still open at the end is not counted.
    """
    reference = ReferenceFilter(kind, max_frame)
    reference.feed_all(events)
    return reference.result
