"""How many camera frames per second a real CAN (FD) bus carries: the bit-level math.

``bus_capacity`` counts every bit a frame costs on the wire, in the phase it is sent in,
for the frames the CAN transport (``hil.adapters.can.link``) sends:

* CAN FD frame with a 29-bit id and bit rate switch. At the **nominal** bitrate: SOF,
  base id, SRR, IDE, extended id, RRS, FDF, res, BRS (36 bits), then CRC delimiter,
  ACK slot, ACK delimiter, EOF (7) and the 3-bit intermission (13 bits). At the
  **data** bitrate: ESI, DLC, the data padded to the next valid FD length (0..8, 12,
  16, 20, 24, 32, 48, 64 bytes), the stuff count (4 bits), CRC-17 (data <= 16 bytes)
  or CRC-21, and its fixed stuff bits (1 + one per 4 bits of stuff count and CRC:
  6 or 7). Dynamic stuff bits over SOF..end of data: worst case one per 4 bits after
  the first, ``floor((n - 1) / 4)``; typical (random data, as JPEG is) one per ~30
  bits (``TYPICAL_STUFF_RATE``, measured by simulating the stuffing rule on random
  bits). Without ``fd`` the frames are classic CAN: 8 data bytes, CRC-15, everything
  at the nominal bitrate (an 8-byte extended frame is 160 bits worst case).
* ISO-TP (ISO 15765-2) for a camera FRAME (the whole PROTOCOL.md encoding: 64-byte
  header + 40 bytes of frame metadata + the JPEG): a first frame (2 bytes of protocol
  control information up to 4095 bytes, else 6), consecutive frames with 1 byte each,
  the last one padded to a valid length, and one flow-control frame back (block
  size 0: one per message).
* Per camera frame, its ESTIMATE: HIL_ESTIMATE (16 bytes), one HIL_ESTIMATE_OBJECT
  (48) per object and HIL_TARGET_TIMESTAMPS (48); more than ``MAX_DBC_OBJECTS``
  objects go over ISO-TP as a whole message. Classic CAN counts each DBC message as
  ``ceil(bytes / 8)`` frames (the DBC frames themselves are CAN FD only).
* Background: clock sync (HIL_SYNC_REQUEST 12 + HIL_SYNC_RESPONSE 32 bytes per
  exchange) and heartbeats (8 bytes, from both sides).

Not counted: error frames and retransmissions, other ECUs' traffic, and the flow-control
turnaround time (latency, not load). python-can's ``virtual`` bus has no bit timing at
all: this applies to real buses (socketcan ``can0``, PCAN, Kvaser, Vector, ...).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hil.common.errors import ConfigError

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
TYPICAL_STUFF_RATE = 0.033  # stuff bits per stuffable bit on random data
PROTOCOL_FRAME_OVERHEAD = 64 + 40  # PROTOCOL.md header + FRAME metadata, bytes
MAX_DBC_OBJECTS = 8  # objects an ESTIMATE carries as DBC frames (more: ISO-TP)
ESTIMATE_BYTES, OBJECT_BYTES, TIMESTAMPS_BYTES = 16, 48, 48  # DBC frame lengths
SYNC_REQUEST_BYTES, SYNC_RESPONSE_BYTES, HEARTBEAT_BYTES = 12, 32, 8
_FD_ARB_BITS = 36  # SOF..BRS of an extended-id CAN FD frame, nominal bitrate
_FD_TAIL_BITS = 13  # CRC delimiter, ACK, ACK delimiter, EOF, intermission
_CLASSIC_STUFFED_BITS = 54  # SOF..DLC (39) + CRC-15 of an extended classic frame
_STUFFING = ("worst", "typical")


def fd_length(data_bytes: int) -> int:
    """The CAN FD frame length (bytes) that carries ``data_bytes``: the next valid DLC.

    Raises:
        ValueError: more than 64 bytes.
    """
    for n in FD_LENGTHS:
        if n >= data_bytes:
            return n
    raise ValueError(f"a CAN FD frame carries at most 64 bytes, not {data_bytes}")


def _stuff(bits: int, stuffing: str) -> float:
    if stuffing == "worst":
        return float((bits - 1) // 4)
    return bits * TYPICAL_STUFF_RATE


def fd_frame_time_s(data_bytes: int, *, bitrate: int, data_bitrate: int, stuffing: str = "worst") -> float:
    """Seconds one extended-id CAN FD frame (bit rate switch on) holds the bus."""
    n = fd_length(data_bytes)
    data_field = 1 + 4 + 8 * n  # ESI, DLC, data
    crc = 17 if n <= 16 else 21
    crc_field = 4 + crc + 1 + (4 + crc) // 4  # stuff count, CRC, fixed stuff bits
    arb_stuff = _stuff(_FD_ARB_BITS, stuffing)
    data_stuff = _stuff(_FD_ARB_BITS + data_field, stuffing) - arb_stuff
    nominal = _FD_ARB_BITS + arb_stuff + _FD_TAIL_BITS
    data = data_field + data_stuff + crc_field
    return nominal / bitrate + data / data_bitrate


def classic_frame_time_s(data_bytes: int, *, bitrate: int, stuffing: str = "worst") -> float:
    """Seconds one extended-id classic CAN frame (0..8 data bytes) holds the bus."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 bytes, not {data_bytes}")
    stuffed = _CLASSIC_STUFFED_BITS + 8 * data_bytes
    return (stuffed + _stuff(stuffed, stuffing) + _FD_TAIL_BITS) / bitrate


def isotp_frame_lengths(message_bytes: int, *, fd: bool) -> list[int]:
    """CAN frame data lengths (bytes, padded) that ISO-TP sends for one message of
    ``message_bytes``, flow control included (block size 0: one flow control)."""
    dl = 64 if fd else 8
    sf_max = dl - 2 if fd else 7
    if message_bytes <= sf_max:
        size = message_bytes + (1 if message_bytes <= 7 else 2)
        return [fd_length(size) if fd else 8]
    ff_data = dl - (2 if message_bytes <= 4095 else 6)
    rest = message_bytes - ff_data
    full, last = divmod(rest, dl - 1)
    frames = [dl] + [dl] * full
    if last:
        frames.append(fd_length(last + 1) if fd else 8)
    frames.append(3 if fd else 8)  # flow control (classic CAN pads it to 8)
    return frames


@dataclass(frozen=True)
class CapacityReport:
    """What the bus carries for one camera stream. Times in seconds, rates in bit/s
    of JPEG payload, loads as fractions of bus time (1.0 = the bus never idle)."""

    bitrate: int
    data_bitrate: int
    fd: bool
    frame_bytes: int
    fps: float
    stuffing: str
    max_load: float
    can_frames_per_camera_frame: int  # ISO-TP frames, flow control included
    camera_frame_time_s: float  # bus time of one camera frame (0 when not over CAN)
    estimate_time_s: float  # bus time of the estimate answering it
    background_load: float  # clock sync + heartbeats
    max_fps: float  # most camera frames per second at max_load
    load: float  # bus load at the requested fps

    @property
    def needed_bps(self) -> float:
        """JPEG bits per second the requested fps sends."""
        return self.fps * self.frame_bytes * 8

    @property
    def carried_bps(self) -> float:
        """JPEG bits per second the bus carries at ``max_load`` beside everything else."""
        return self.max_fps * self.frame_bytes * 8

    def check(self) -> None:
        """Raise ``ConfigError`` when the requested fps needs more than the bus carries."""
        if self.load <= self.max_load:
            return
        rates = f"{_rate(self.bitrate)}/{_rate(self.data_bitrate)}" if self.fd else f"{_rate(self.bitrate)} (classic CAN)"
        limit = math.floor(self.max_fps * 10) / 10
        load = f" at most {self.max_load:.0%} bus load" if self.max_load < 1 else ""
        raise ConfigError(
            f"camera.fps={self.fps:g} needs {self.needed_bps / 1e6:.1f} Mbit/s but the bus carries "
            f"{self.carried_bps / 1e6:.1f} Mbit/s at bitrate {rates}{load} (a {self.frame_bytes}-byte "
            f"JPEG costs {self.camera_frame_time_s * 1e3:.1f} ms of bus time, its estimate "
            f"{self.estimate_time_s * 1e3:.2f} ms); lower fps to \u2264 {limit:g}, lower "
            f"jpeg_quality/resolution, or send frames over zenoh (mixed target)")


def _rate(bps: int) -> str:
    if bps % 1_000_000 == 0:
        return f"{bps // 1_000_000}M"
    if bps % 1000 == 0:
        return f"{bps // 1000}k"
    return f"{bps}"


def bus_capacity(*, bitrate: int, data_bitrate: int, fd: bool, frame_bytes: int, fps: float,
                 objects_per_estimate: int = 0, sync_hz: float = 10.0, heartbeat_hz: float = 4.0,
                 camera_over: str = "isotp", stuffing: str = "worst", max_load: float = 1.0) -> CapacityReport:
    """Achievable camera frame rate and bus load for JPEG frames of ``frame_bytes``.

    Args:
        bitrate: nominal (arbitration) bitrate, bit/s.
        data_bitrate: CAN FD data-phase bitrate, bit/s (ignored without ``fd``).
        fd: CAN FD frames (64 bytes) or classic CAN (8 bytes).
        frame_bytes: JPEG size of one camera frame, bytes.
        fps: requested camera frames per second.
        objects_per_estimate: objects each estimate carries.
        sync_hz: clock-sync exchanges per second; heartbeat_hz: heartbeats per second
            from each side (the transport sends 4).
        camera_over: ``"isotp"`` (frames on this bus) or ``"none"`` (a mixed target:
            frames travel over another transport, only estimates here).
        stuffing: ``"worst"`` (guaranteed) or ``"typical"`` (random data).
        max_load: the bus load ``check()`` allows (1.0: all of it).

    Raises:
        ConfigError: a value out of range (names it).
    """
    _check_args(bitrate, data_bitrate, fd, frame_bytes, fps, objects_per_estimate, sync_hz,
                heartbeat_hz, camera_over, stuffing, max_load)

    def frame_time(n: int) -> float:
        if fd:
            return fd_frame_time_s(n, bitrate=bitrate, data_bitrate=data_bitrate, stuffing=stuffing)
        return classic_frame_time_s(n, bitrate=bitrate, stuffing=stuffing)

    def dbc_time(n: int) -> float:  # one DBC message of n bytes
        if fd:
            return frame_time(n)
        return sum(frame_time(min(8, n - i)) for i in range(0, n, 8))

    def isotp_time(n: int) -> tuple[float, int]:
        lengths = isotp_frame_lengths(n, fd=fd)
        return sum(frame_time(x) for x in lengths), len(lengths)

    camera_s, n_frames = isotp_time(frame_bytes + PROTOCOL_FRAME_OVERHEAD) if camera_over == "isotp" else (0.0, 0)
    if objects_per_estimate <= MAX_DBC_OBJECTS:
        estimate_s = (dbc_time(ESTIMATE_BYTES) + objects_per_estimate * dbc_time(OBJECT_BYTES)
                      + dbc_time(TIMESTAMPS_BYTES))
    else:
        estimate_s = isotp_time(64 + 16 + 36 * objects_per_estimate)[0]
    background = (sync_hz * (dbc_time(SYNC_REQUEST_BYTES) + dbc_time(SYNC_RESPONSE_BYTES))
                  + 2 * heartbeat_hz * dbc_time(HEARTBEAT_BYTES))
    per_frame = camera_s + estimate_s
    max_fps = max(0.0, (max_load - background) / per_frame)
    return CapacityReport(bitrate=bitrate, data_bitrate=data_bitrate, fd=fd, frame_bytes=frame_bytes,
                          fps=fps, stuffing=stuffing, max_load=max_load,
                          can_frames_per_camera_frame=n_frames, camera_frame_time_s=camera_s,
                          estimate_time_s=estimate_s, background_load=background, max_fps=max_fps,
                          load=background + fps * per_frame)


def _check_args(bitrate: int, data_bitrate: int, fd: bool, frame_bytes: int, fps: float, objects: int,
                sync_hz: float, heartbeat_hz: float, camera_over: str, stuffing: str, max_load: float) -> None:
    if bitrate <= 0:
        raise ConfigError(f"can bitrate={bitrate}: expected a positive bit/s, e.g. 500000")
    if fd and data_bitrate < bitrate:
        raise ConfigError(f"can data_bitrate={data_bitrate} is below bitrate={bitrate}; CAN FD's data "
                          f"phase is at least as fast, e.g. 2000000")
    if frame_bytes < 0 or fps <= 0 or objects < 0 or sync_hz < 0 or heartbeat_hz < 0:
        raise ConfigError(f"bus_capacity needs frame_bytes >= 0, fps > 0 and objects, sync_hz, "
                          f"heartbeat_hz >= 0; got frame_bytes={frame_bytes}, fps={fps}, "
                          f"objects_per_estimate={objects}, sync_hz={sync_hz}, heartbeat_hz={heartbeat_hz}")
    if camera_over not in ("isotp", "none"):
        raise ConfigError(f"camera_over={camera_over!r}; expected 'isotp' or 'none'")
    if stuffing not in _STUFFING:
        raise ConfigError(f"stuffing={stuffing!r}; expected one of {', '.join(_STUFFING)}")
    if not 0 < max_load <= 1:
        raise ConfigError(f"max_load={max_load}; expected a fraction in (0, 1]")


__all__ = ["CapacityReport", "bus_capacity", "classic_frame_time_s", "fd_frame_time_s", "fd_length",
           "isotp_frame_lengths"]
