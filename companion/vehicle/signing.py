"""MAVLink 2 message signing for the link to the autopilot, which MAVSDK 4.1 cannot do itself.

`SigningRelay(vehicle_url, key)` stands between MAVSDK and the autopilot. `start()` binds a UDP
socket on 127.0.0.1 (loopback only), opens the vehicle side, runs one thread, and returns the URL
MAVSDK must connect to instead of `vehicle_url` (`udpout://127.0.0.1:PORT`). `stop()` ends the
thread and closes every socket and device; it is idempotent, and the relay is a context manager.

- MAVSDK to vehicle: each frame is decoded with pymavlink and packed again as MAVLink 2, signed
  with the key (pymavlink's signing), with the sender's own system id, component id, sequence
  number and payload. The relay only accepts the first local sender it hears (MAVSDK's socket)
  for its lifetime: a new MAVSDK instance needs a new relay. Frames pymavlink cannot pack
  (message ids its dialect does not know) and malformed frames are dropped and counted.
- Vehicle to MAVSDK: only frames with a valid signature are forwarded, byte for byte (MAVSDK
  without a key ignores the signature block). Unsigned, wrongly signed, replayed and too old
  frames are dropped and counted: nobody without the key can inject anything towards MAVSDK.
- Replay protection is pymavlink's, per (link id, system, component) stream: a timestamp must
  grow, and a new stream may be at most one minute behind our own timestamp. Our timestamp starts
  at the wall clock (10 us units since 2015-01-01) and follows the largest valid timestamp
  received, as the MAVLink C library does. Unlike pymavlink's own check, a frame whose signature
  is wrong never moves a stream's timestamp (`check_signature` here), so a forged frame with a
  huge timestamp cannot lock the real sender out.
- Vehicle URLs (MAVSDK's syntax): `udpin://HOST:PORT` (bind there; send to whoever sent validly
  signed frames, as MAVSDK's udpin answers its senders), `udp://` (same, MAVSDK's deprecated
  spelling), `udpout://HOST:PORT` (send there), `serial:///dev/ttyX:BAUD` (raw termios, 8N1, no
  flow control; standard baud rates only). TCP is not supported. A bad URL raises
  `ConfigError("vehicle.connection", ...)`.

`load_signing_key(path)` reads the key file: 64 hexadecimal digits (the 32-byte secret; a final
newline is fine). It refuses, with `ConfigError("vehicle.signing_key_file", why)`, a missing file,
a symbolic link, anything but a regular file, a file of another user, a file that group or others
may read or write (mode & 0o077), and a key that is not 32 bytes or is all zeros (a zero key turns
signing off in SETUP_SIGNING). `key_from_passphrase` gives the key MAVProxy's `signing setup` and
QGroundControl derive from a passphrase (SHA-256 of it).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import select
import socket
import stat
import termios
import threading
import time
import tty
from dataclasses import dataclass, replace
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError

__all__ = ["KEY_BYTES", "RelayCounters", "Signature", "SigningRelay", "check_signature",
           "is_signed", "key_from_passphrase", "load_signing_key", "new_signer",
           "signing_timestamp_now"]

KEY_BYTES = 32
KEY_FILE_CONFIG = "vehicle.signing_key_file"
URL_CONFIG = "vehicle.connection"
SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01 00:00:00 UTC: MAVLink's signing time origin
SIGNING_TICKS_PER_S = 100_000  # timestamps count 10 us ticks
_SIGNATURE_BLOCK_BYTES = 13  # link id (1), timestamp (6), signature (6)
_V2_HEADER_BYTES = 10
_V2_MAGIC = 0xFD
_MAX_DATAGRAM = 65535
_MAX_KEY_FILE_BYTES = 1024
_POLL_S = 0.5  # the thread also wakes at once on stop(); this only bounds a lost wake-up
_MAX_UDP_REMOTES = 8


class Signature(Enum):
    """The signing state of one received frame."""

    VALID = "valid"
    UNSIGNED = "unsigned"
    INVALID = "invalid"  # wrong key, corrupted, replayed or too old


@dataclass(frozen=True, slots=True)
class RelayCounters:
    """Frames through the relay so far (a snapshot)."""

    to_vehicle: int = 0  # MAVSDK frames signed and sent to the autopilot
    to_mavsdk: int = 0  # autopilot frames with a valid signature forwarded to MAVSDK
    dropped_unsigned: int = 0  # vehicle side: frames without a signature
    dropped_bad_signature: int = 0  # vehicle side: wrong key, corrupted, replayed or too old
    dropped_malformed: int = 0  # either side: bytes that are no MAVLink frame (bad CRC, garbage)
    dropped_unsignable: int = 0  # MAVSDK side: message ids pymavlink's dialect does not know
    dropped_foreign: int = 0  # MAVSDK side: from a local sender other than the MAVSDK it locked on
    dropped_no_route: int = 0  # nobody to send to yet (MAVSDK silent so far, udpin vehicle unheard)
    vehicle_errors: int = 0  # failed reads or writes on the vehicle side (a serial device gone)


# -- signing primitives (pymavlink's) ----------------------------------------------------------


def signing_timestamp_now() -> int:
    """The wall clock as a MAVLink signing timestamp (10 us ticks since 2015-01-01 UTC)."""
    return int((max(time.time(), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S)
               * SIGNING_TICKS_PER_S)


def new_signer(key: bytes, system_id: int = 0, component_id: int = 0,
               link_id: int = 0) -> mavlink.MAVLink:
    """A pymavlink MAVLink that signs what it packs and holds the replay state of what it checks.

    Frames are parsed by a separate MAVLink without a key (pymavlink's own check would run in the
    parser, see `check_signature`), and checked with this one.
    """
    if len(key) != KEY_BYTES:
        raise ValueError(f"a signing key has {KEY_BYTES} bytes, not {len(key)}")
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.signing.secret_key = bytes(key)
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = signing_timestamp_now()
    return mav


def is_signed(frame: bytes | bytearray) -> bool:
    """Whether a frame is MAVLink 2 with the signed flag (it claims a signature)."""
    return len(frame) > 2 and frame[0] == _V2_MAGIC and bool(
        frame[2] & mavlink.MAVLINK_IFLAG_SIGNED)


def check_signature(signer: mavlink.MAVLink, frame: bytes | bytearray) -> Signature:
    """Check one whole received frame's signature with pymavlink's `MAVLink.check_signature`.

    pymavlink records a stream's new timestamp before it compares the signature; here a frame
    that fails leaves the stream's record as it was (the MAVLink C library's order), so only
    frames signed with the key move the replay window.
    """
    if not is_signed(frame):
        return Signature.UNSIGNED
    if len(frame) < _V2_HEADER_BYTES + 2 + _SIGNATURE_BLOCK_BYTES:
        return Signature.INVALID
    system_id, component_id = frame[5], frame[6]
    stream = (frame[-_SIGNATURE_BLOCK_BYTES], system_id, component_id)
    streams: dict[tuple[int, int, int], int] = signer.signing.stream_timestamps
    before = streams.get(stream)
    if signer.check_signature(bytearray(frame), system_id, component_id):
        return Signature.VALID
    if before is None:
        streams.pop(stream, None)
    else:
        streams[stream] = before
    return Signature.INVALID


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte key MAVProxy (`signing setup`) and QGroundControl derive: SHA-256 of it."""
    return hashlib.sha256(passphrase.encode()).digest()


# -- the key file ------------------------------------------------------------------------------


def load_signing_key(path: Path) -> bytes:
    """The 32-byte key in path (64 hex digits), or ConfigError naming vehicle.signing_key_file."""
    def refuse(problem: str) -> ConfigError:
        return ConfigError(KEY_FILE_CONFIG, f"{path}: {problem}")

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise refuse("no such file") from None
    except OSError as exc:
        if path.is_symlink():
            raise refuse("is a symbolic link; point the setting at the key file itself") from None
        raise refuse(f"cannot open it: {exc.strerror}") from None
    try:
        info = os.fstat(fd)  # of the file opened, not of whatever the path names by now
        if not stat.S_ISREG(info.st_mode):
            raise refuse("is not a regular file")
        if info.st_uid != os.geteuid():
            raise refuse(f"belongs to user id {info.st_uid}, not to this service's "
                         f"({os.geteuid()}); chown it")
        mode = stat.S_IMODE(info.st_mode)
        if mode & 0o077:
            raise refuse(f"mode {mode:04o} lets group or others read or write the signing "
                         "key; chmod 600 it (and make a new key if others may have read it)")
        data = os.read(fd, _MAX_KEY_FILE_BYTES + 1)
    finally:
        os.close(fd)
    try:
        text = data.decode("ascii").strip()
        key = bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        raise refuse(f"must hold {2 * KEY_BYTES} hexadecimal digits (a {KEY_BYTES}-byte key), "
                     "and does not") from None
    if len(key) != KEY_BYTES:
        raise refuse(f"holds a {len(key)}-byte key; a MAVLink signing key has {KEY_BYTES} bytes "
                     f"({2 * KEY_BYTES} hexadecimal digits)")
    if not any(key):
        raise refuse("holds the all-zero key, which means 'signing off' in SETUP_SIGNING")
    return key


# -- the vehicle side --------------------------------------------------------------------------


Address = tuple[str, int]


class _VehicleSide(Protocol):
    def fileno(self) -> int: ...

    def receive(self) -> list[tuple[bytes, Address | None]]: ...

    def learn(self, source: Address | None) -> None: ...

    def send(self, data: bytes) -> bool: ...

    def close(self) -> None: ...


class _UdpVehicle:
    """udpin (bind, answer signed senders) or udpout (send to a fixed address)."""

    def __init__(self, host: str, port: int, listen: bool) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port) if listen else ("0.0.0.0", 0))
            self._remotes: list[Address] = [] if listen else [
                (socket.gethostbyname(host), port)]
        except OSError:
            self._sock.close()
            raise
        self._sock.setblocking(False)
        self._listen = listen

    def fileno(self) -> int:
        return self._sock.fileno()

    def receive(self) -> list[tuple[bytes, Address | None]]:
        out: list[tuple[bytes, Address | None]] = []
        while True:
            try:
                data, addr = self._sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionError:  # ICMP port unreachable from a gone peer
                continue
            out.append((data, (str(addr[0]), int(addr[1]))))

    def learn(self, source: Address | None) -> None:
        """A validly signed frame came from source: answer there too (udpin only)."""
        if not self._listen or source is None or source in self._remotes:
            return
        self._remotes.append(source)
        del self._remotes[:-_MAX_UDP_REMOTES]

    def send(self, data: bytes) -> bool:
        for remote in self._remotes:
            with contextlib.suppress(OSError):
                self._sock.sendto(data, remote)
        return bool(self._remotes)

    def close(self) -> None:
        self._sock.close()


class _SerialVehicle:
    """A serial port in raw mode (termios): 8 data bits, no parity, 1 stop bit, no flow control."""

    def __init__(self, path: str, baud: int) -> None:
        speed = getattr(termios, f"B{baud}", None)
        if speed is None:
            raise ValueError(f"{baud} is not a standard baud rate")
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
        try:
            tty.setraw(self._fd, termios.TCSANOW)
            attrs = termios.tcgetattr(self._fd)
            attrs[2] = (attrs[2] | termios.CLOCAL | termios.CREAD) & ~termios.CRTSCTS
            attrs[4] = attrs[5] = speed
            termios.tcsetattr(self._fd, termios.TCSANOW, attrs)
            os.set_blocking(self._fd, True)  # reads only follow select(); writes may wait
        except (OSError, termios.error):
            os.close(self._fd)
            raise

    def fileno(self) -> int:
        return self._fd

    def receive(self) -> list[tuple[bytes, Address | None]]:
        try:
            data = os.read(self._fd, 4096)
        except (BlockingIOError, InterruptedError):
            return []
        return [(data, None)] if data else []

    def learn(self, source: Address | None) -> None:
        return

    def send(self, data: bytes) -> bool:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]
        return True

    def close(self) -> None:
        os.close(self._fd)


def _parse_url(url: str) -> tuple[str, str, int]:
    """(scheme, host or device path, port or baud) of a MAVSDK connection URL."""
    scheme, sep, rest = url.partition("://")
    scheme = scheme.lower()
    if not sep or scheme not in ("udpin", "udp", "udpout", "serial"):
        raise ConfigError(URL_CONFIG, f"{url!r}: the signing relay supports udpin://HOST:PORT, "
                                      "udpout://HOST:PORT and serial:///dev/DEVICE:BAUD")
    where, colon, number = rest.rpartition(":")
    if not colon or not where or not number.isdigit():
        raise ConfigError(URL_CONFIG, f"{url!r}: expected {scheme}://"
                          + ("/dev/DEVICE:BAUD" if scheme == "serial" else "HOST:PORT"))
    value = int(number)
    if scheme != "serial" and not 0 < value < 65536:
        raise ConfigError(URL_CONFIG, f"{url!r}: port {value} is out of range")
    return ("udpin" if scheme == "udp" else scheme), where, value


def _open_vehicle(url: str) -> _VehicleSide:
    scheme, where, number = _parse_url(url)
    try:
        if scheme == "serial":
            return _SerialVehicle(where, number)
        return _UdpVehicle(where, number, listen=scheme == "udpin")
    except (OSError, ValueError, termios.error) as exc:
        raise ConfigError(URL_CONFIG, f"{url!r}: cannot open it: {exc}") from exc


# -- the relay ---------------------------------------------------------------------------------


def _frames(data: bytes) -> list[mavlink.MAVLink_message]:
    """The frames of one datagram, parsed on their own (no state shared across senders)."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser.parse_buffer(data) or []


class SigningRelay:
    """MAVSDK <-> (signs, verifies) <-> autopilot; see the module docstring."""

    def __init__(self, vehicle_url: str, key: bytes, *, link_id: int = 0,
                 accept_unsigned_ids: frozenset[int] = frozenset()) -> None:
        _parse_url(vehicle_url)  # a bad URL fails here, before anything is opened
        if len(key) != KEY_BYTES:
            raise ValueError(f"a signing key has {KEY_BYTES} bytes, not {len(key)}")
        if not 0 <= link_id <= 255:
            raise ValueError(f"link_id {link_id} is not in 0..255")
        self.vehicle_url = vehicle_url
        self._key = bytes(key)
        self._link_id = link_id
        self._accept_unsigned = accept_unsigned_ids  # vehicle-side ids let through unsigned
        self._lock = threading.Lock()
        self._counters = RelayCounters()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._mavsdk_sock: socket.socket | None = None
        self._vehicle: _VehicleSide | None = None
        self._wake: tuple[socket.socket, socket.socket] | None = None
        self._mavsdk_peer: Address | None = None
        self._vehicle_parser = mavlink.MAVLink(None)  # a serial stream keeps its parse state
        self._vehicle_parser.robust_parsing = True
        self._signer = new_signer(self._key, link_id=link_id)
        self.mavsdk_url = ""

    # -- lifecycle --------------------------------------------------------------------------

    def start(self) -> str:
        """Open both sides, run the thread; the URL MAVSDK connects to (udpout://127.0.0.1:P)."""
        if self._thread is not None:
            return self.mavsdk_url
        self._stopping.clear()
        mavsdk_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            mavsdk_sock.bind(("127.0.0.1", 0))
            mavsdk_sock.setblocking(False)
            self._vehicle = _open_vehicle(self.vehicle_url)
        except BaseException:
            mavsdk_sock.close()
            raise
        self._mavsdk_sock = mavsdk_sock
        self._wake = socket.socketpair()
        self._signer = new_signer(self._key, link_id=self._link_id)
        self._vehicle_parser = mavlink.MAVLink(None)
        self._vehicle_parser.robust_parsing = True
        self._mavsdk_peer = None
        port = int(mavsdk_sock.getsockname()[1])
        self.mavsdk_url = f"udpout://127.0.0.1:{port}"
        self._thread = threading.Thread(target=self._run, name="signing-relay", daemon=True)
        self._thread.start()
        return self.mavsdk_url

    def stop(self) -> None:
        """Stop the thread, close every socket and the device. Idempotent."""
        self._stopping.set()
        if self._wake is not None:
            with contextlib.suppress(OSError):
                self._wake[1].send(b"x")
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for closable in (self._mavsdk_sock, self._vehicle, *(self._wake or ())):
            if closable is not None:
                with contextlib.suppress(OSError):
                    closable.close()
        self._mavsdk_sock = self._vehicle = self._wake = None

    def __enter__(self) -> SigningRelay:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    @property
    def counters(self) -> RelayCounters:
        """What went through and what was dropped so far."""
        with self._lock:
            return self._counters

    @property
    def mavsdk_port(self) -> int:
        """The loopback UDP port MAVSDK sends to (0 before start)."""
        sock = self._mavsdk_sock
        return int(sock.getsockname()[1]) if sock is not None else 0

    def _count(self, **increments: int) -> None:
        with self._lock:
            c = self._counters
            self._counters = replace(c, **{k: getattr(c, k) + v for k, v in increments.items()})

    # -- the thread -------------------------------------------------------------------------

    def _run(self) -> None:
        mavsdk_sock, vehicle, wake = self._mavsdk_sock, self._vehicle, self._wake
        assert mavsdk_sock is not None and vehicle is not None and wake is not None
        mavsdk_fd, vehicle_fd = mavsdk_sock.fileno(), vehicle.fileno()
        while not self._stopping.is_set():
            try:
                ready, _, _ = select.select([mavsdk_fd, vehicle_fd, wake[0].fileno()], [], [],
                                            _POLL_S)
            except (OSError, ValueError):  # closed under us: stop() is under way
                return
            if mavsdk_fd in ready:
                self._from_mavsdk(mavsdk_sock, vehicle)
            if vehicle_fd in ready:
                self._from_vehicle(mavsdk_sock, vehicle)

    def _from_mavsdk(self, sock: socket.socket, vehicle: _VehicleSide) -> None:
        while True:
            try:
                data, addr = sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionError:
                continue
            source = (str(addr[0]), int(addr[1]))
            if self._mavsdk_peer is None:
                self._mavsdk_peer = source
            elif source != self._mavsdk_peer:
                self._count(dropped_foreign=1)
                continue
            for msg in _frames(data):
                self._sign_and_send(msg, vehicle)

    def _sign_and_send(self, msg: mavlink.MAVLink_message, vehicle: _VehicleSide) -> None:
        if isinstance(msg, mavlink.MAVLink_bad_data):
            self._count(dropped_malformed=1)
            return
        if isinstance(msg, mavlink.MAVLink_unknown):
            self._count(dropped_unsignable=1)
            return
        signer = self._signer
        signer.srcSystem, signer.srcComponent = msg.get_srcSystem(), msg.get_srcComponent()
        signer.seq = msg.get_seq()
        packed = msg.pack(signer)
        try:
            sent = vehicle.send(packed)
        except OSError:
            self._count(vehicle_errors=1)
            return
        self._count(**{"to_vehicle" if sent else "dropped_no_route": 1})

    def _from_vehicle(self, mavsdk_sock: socket.socket, vehicle: _VehicleSide) -> None:
        try:
            received = vehicle.receive()
        except OSError:  # e.g. a USB serial adapter unplugged: do not spin on it
            self._count(vehicle_errors=1)
            self._stopping.wait(_POLL_S)
            return
        for data, source in received:
            if source is None:  # a byte stream: frames may span reads
                messages = self._vehicle_parser.parse_buffer(data) or []
            else:
                messages = _frames(data)
            for msg in messages:
                self._verify_and_forward(msg, source, mavsdk_sock, vehicle)

    def _verify_and_forward(self, msg: mavlink.MAVLink_message, source: Address | None,
                            mavsdk_sock: socket.socket, vehicle: _VehicleSide) -> None:
        if isinstance(msg, mavlink.MAVLink_bad_data):
            self._count(dropped_malformed=1)
            return
        frame = bytes(msg.get_msgbuf())
        verdict = check_signature(self._signer, frame)
        if verdict is Signature.INVALID:
            self._count(dropped_bad_signature=1)
            return
        if verdict is Signature.UNSIGNED and msg.get_msgId() not in self._accept_unsigned:
            self._count(dropped_unsigned=1)
            return
        if verdict is Signature.VALID:
            vehicle.learn(source)
        peer = self._mavsdk_peer
        if peer is None:
            self._count(dropped_no_route=1)
            return
        with contextlib.suppress(OSError):
            mavsdk_sock.sendto(frame, peer)
        self._count(to_mavsdk=1)
