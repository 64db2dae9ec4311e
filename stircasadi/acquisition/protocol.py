"""Wire formats shared by the instrument drivers and their emulators.

When to use: a driver (``scope``, ``scan``, ``counter``) frames its commands and parses its
replies with these functions; the emulators (``emulators``) build their replies with the same
functions, so the two ends can never disagree about a format.

IEEE-488.2 definite-length arbitrary block (section 8.7.9 of the standard)::

    #<n><length: n ASCII digits><length bytes of binary payload>[terminator]

``n`` is one digit 1..9, the count of length digits. Example: ``#15hello`` is the 5-byte block
``hello``. ``#0`` (indefinite length, terminated by LF + END) is refused: with binary data a LF
may be part of the payload, so only the definite form is binary-safe.

Line protocol (scan controller, counter): ASCII lines ending in the terminator (LF by default).
A line holds printable ASCII only (0x20..0x7E); anything else is garbage on the wire and is
reported as such, never guessed at.

Neglects: VXI-11/USBTMC framing (the drivers speak over a serial byte stream only).
"""
from __future__ import annotations

from ..errors import InstrumentError

#: the largest payload a block header can announce (9 length digits)
MAX_BLOCK_DIGITS = 9


def encode_block(payload: bytes) -> bytes:
    """Frame ``payload`` as an IEEE-488.2 definite-length block (no terminator)."""
    payload = bytes(payload)
    digits = str(len(payload))
    if len(digits) > MAX_BLOCK_DIGITS:
        raise InstrumentError(f"a definite-length block holds at most 999999999 bytes; got "
                              f"{len(payload)}. Split the transfer.")
    return b"#" + str(len(digits)).encode("ascii") + digits.encode("ascii") + payload


def preview(data: bytes, limit: int = 48) -> str:
    """A short printable rendering of bytes that arrived (for error messages)."""
    data = bytes(data)
    shown = data[:limit]
    more = f" ... (+{len(data) - limit} more bytes)" if len(data) > limit else ""
    return f"{shown!r}{more} [{len(data)} bytes]"


def parse_block_header(head: bytes) -> tuple[int, int]:
    """Parse the start of a block.

    Parameters
    ----------
    head : bytes
        At least ``2`` bytes starting with ``#``; more is allowed.

    Returns
    -------
    (header_length, payload_length) : tuple of int
        ``header_length`` is ``2 + n``. Raises ``InstrumentError`` if ``head`` is too short
        to hold the full header (the caller reads more and calls again) -- use
        :func:`block_header_need` to know how many bytes are needed.
    """
    if len(head) < 2 or head[:1] != b"#":
        raise InstrumentError(f"an IEEE-488.2 block must start with '#<digit>'; got {preview(head)}.")
    nd = head[1:2]
    if not nd.isdigit():
        raise InstrumentError(f"an IEEE-488.2 block header '#<n>' needs a digit n in 1..9 after '#'; "
                              f"got {preview(head[:12])}.")
    n = int(nd)
    if n == 0:
        raise InstrumentError("indefinite-length block '#0' is not binary-safe and is refused; set "
                              "the instrument to definite-length blocks (e.g. 'DEF9' / 'CURVE?' "
                              "with a '#<n><len>' header).")
    if len(head) < 2 + n:
        raise InstrumentError(f"block header announces {n} length digits but only "
                              f"{len(head) - 2} arrived: {preview(head)}.")
    digits = head[2:2 + n]
    if not digits.isdigit():
        raise InstrumentError(f"block header length field must be {n} ASCII digits; got "
                              f"{preview(digits)}.")
    return 2 + n, int(digits)


def decode_block(data: bytes, terminator: bytes = b"\n") -> bytes:
    """Decode one complete block (optionally followed by ``terminator``) and return its payload.

    Raises ``InstrumentError`` on a malformed header, a short payload (truncated block) or
    trailing bytes other than the terminator.
    """
    data = bytes(data)
    start = 0
    while start < len(data) and data[start:start + 1] in (b" ", b"\r", b"\n"):
        start += 1
    data = data[start:]
    hlen, length = parse_block_header(data)
    payload = data[hlen:hlen + length]
    if len(payload) < length:
        raise InstrumentError(f"truncated IEEE-488.2 block: header announced {length} bytes, "
                              f"{len(payload)} arrived ({preview(data)}).")
    rest = data[hlen + length:]
    if rest and rest != terminator and rest.strip(b"\r\n") != b"":
        raise InstrumentError(f"{len(rest)} unexpected byte(s) after a {length}-byte block: "
                              f"{preview(rest)}.")
    return payload


def check_line(raw: bytes) -> str:
    """Decode one received line (terminator already stripped) as printable ASCII.

    Raises ``InstrumentError`` naming the bad bytes when the line holds anything else.
    """
    raw = bytes(raw).rstrip(b"\r")
    bad = [b for b in raw if b < 0x20 or b > 0x7E]
    if bad:
        raise InstrumentError(f"garbage on the line: {len(bad)} non-printable byte(s) in "
                              f"{preview(raw)}; a reply must be printable ASCII.")
    return raw.decode("ascii")
