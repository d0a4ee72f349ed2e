"""MAVLink 2 signing: the signing mock autopilot, the signing relay in front of MAVSDK, key files.

Everything is real MAVLink over loopback UDP (or a pseudo-terminal for the serial side) on free
ports, and every autopilot, relay and socket is stopped in a fixture or a finally block.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import secrets
import select
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync, ActionError, ActionResult
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError
from companion.geo import LocalNed
from companion.sim.scenario import load_scenario
from companion.vehicle.mavsdk_link import MavsdkLink
from companion.vehicle.signing import (
    RelayCounters,
    Signature,
    SigningRelay,
    check_signature,
    is_signed,
    key_from_passphrase,
    load_signing_key,
    new_signer,
)
from sitl.autopilot import AutopilotConfig, MockAutopilot, Snapshot
from sitl.cli import sitl_scenarios
from sitl.clock import SimClock
from sitl.link import UdpLink, free_udp_port
from sitl.modes import Flavour
from sitl.runner import Sitl
from tests.mavlink_client import Client

pytestmark = pytest.mark.sitl

SPEEDUP = 4.0
GEO = LocalNed(37.2, -80.4, 600.0)
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
WAIT_S = 5.0


@pytest.fixture
def key() -> bytes:
    return secrets.token_bytes(32)


def _until(condition: Callable[[], bool], timeout_s: float = WAIT_S) -> None:
    """Poll a condition until it holds (AssertionError after timeout_s)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met within the timeout")
        time.sleep(0.01)


def _receive_until(receive: Callable[[], list[mavlink.MAVLink_message]],
                   done: Callable[[list[mavlink.MAVLink_message]], bool],
                   timeout_s: float = WAIT_S) -> list[mavlink.MAVLink_message]:
    """Everything receive() gives until done(all so far) (AssertionError after timeout_s)."""
    got: list[mavlink.MAVLink_message] = []
    deadline = time.monotonic() + timeout_s
    while not done(got):
        if time.monotonic() > deadline:
            raise AssertionError(f"not done within the timeout; got {got}")
        got += receive()  # each call waits a little for data
    return got


@contextlib.contextmanager
def _autopilot(remote_port: int, key: bytes | None, flavour: Flavour = Flavour.PX4
               ) -> Iterator[MockAutopilot]:
    link = UdpLink([("127.0.0.1", remote_port)], np.random.default_rng(0))
    autopilot = MockAutopilot(
        AutopilotConfig(flavour=flavour, armable_after_s=0.0, signing_key=key), link,
        SimClock(SPEEDUP), GEO)
    autopilot.start()
    try:
        yield autopilot
    finally:
        autopilot.stop()


def _arm_frame(mav: mavlink.MAVLink, arm: bool = True) -> bytes:
    return bytes(mav.command_long_encode(1, 1, ARM, 0, 1.0 if arm else 0.0, 0, 0, 0, 0, 0, 0)
                 .pack(mav))


def _acks(messages: list[mavlink.MAVLink_message]) -> list[mavlink.MAVLink_message]:
    return [m for m in messages if m.get_type() == "COMMAND_ACK" and m.command == ARM]


def _send_rejected(client: Client, autopilot: MockAutopilot, frame: bytes,
                   counter: Callable[[Snapshot], int]) -> None:
    """Send frame; it must be counted as rejected, draw no ack, and leave the vehicle disarmed."""
    before = counter(autopilot.snapshot())
    assert client.autopilot is not None
    client.sock.sendto(frame, client.autopilot)
    _until(lambda: counter(autopilot.snapshot()) > before)
    assert not _acks(client.messages(0.2))  # an accepted command is acked in the same step
    assert not autopilot.snapshot().armed


# ---------------------------------------------------------------------------- the autopilot


@pytest.mark.parametrize("flavour", [Flavour.PX4, Flavour.ARDUPILOT], ids=lambda f: f.value)
def test_signing_autopilot_rejects_unsigned_and_wrong_key_accepts_the_key(
        client: Client, key: bytes, flavour: Flavour) -> None:
    with _autopilot(client.port, key, flavour) as autopilot:
        heartbeat = client.wait_type("HEARTBEAT")
        assert is_signed(heartbeat.get_msgbuf())
        assert check_signature(new_signer(key), heartbeat.get_msgbuf()) is Signature.VALID

        _send_rejected(client, autopilot, _arm_frame(client.mav), lambda s: s.rejected_unsigned)
        wrong = new_signer(secrets.token_bytes(32), 255, 190)
        _send_rejected(client, autopilot, _arm_frame(wrong), lambda s: s.rejected_bad_signature)

        client.mav = new_signer(key, 255, 190)
        assert client.command(ARM, 1).result == ACCEPTED
        assert autopilot.snapshot().armed
        snap = autopilot.snapshot()
        assert (snap.rejected_unsigned, snap.rejected_bad_signature) == (1, 1)


@pytest.mark.parametrize(("flavour", "heartbeat_rejected"),
                         [(Flavour.PX4, 0), (Flavour.ARDUPILOT, 1)], ids=["px4", "ardupilot"])
def test_the_unsigned_allow_list_follows_the_flavour(client: Client, key: bytes, flavour: Flavour,
                                                     heartbeat_rejected: int) -> None:
    """PX4 takes an unsigned HEARTBEAT (its allow-list), ArduPilot does not; RADIO_STATUS both."""
    unsigned = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    heartbeat = bytes(unsigned.heartbeat_encode(6, 8, 0, 0, 4).pack(unsigned))
    radio = bytes(unsigned.radio_status_encode(200, 190, 90, 10, 12, 0, 0).pack(unsigned))
    with _autopilot(client.port, key, flavour) as autopilot:
        client.wait_type("HEARTBEAT")
        assert client.autopilot is not None
        for frame in (heartbeat, radio, _arm_frame(unsigned)):  # the arm, last, is rejected
            client.sock.sendto(frame, client.autopilot)
        _until(lambda: autopilot.snapshot().rejected_unsigned == heartbeat_rejected + 1)


def test_a_replayed_signed_command_is_rejected(client: Client, key: bytes) -> None:
    with _autopilot(client.port, key) as autopilot:
        client.wait_type("HEARTBEAT")
        client.mav = new_signer(key, 255, 190)
        captured = _arm_frame(client.mav)  # what an eavesdropper records
        assert client.autopilot is not None
        client.sock.sendto(captured, client.autopilot)
        assert _acks([client.wait_type("COMMAND_ACK")])[0].result == ACCEPTED
        assert autopilot.snapshot().armed
        assert client.command(ARM, 0).result == ACCEPTED  # disarmed, with a newer timestamp
        _send_rejected(client, autopilot, captured, lambda s: s.rejected_bad_signature)


def test_a_forged_frame_cannot_push_a_stream_timestamp(key: bytes) -> None:
    """pymavlink alone would record the forger's huge timestamp and refuse the real sender."""
    sender, receiver = new_signer(key, 255, 190), new_signer(key)
    assert check_signature(receiver, _arm_frame(sender)) is Signature.VALID
    forger = new_signer(secrets.token_bytes(32), 255, 190)
    forger.signing.timestamp = sender.signing.timestamp + 10**9
    assert check_signature(receiver, _arm_frame(forger)) is Signature.INVALID
    assert check_signature(receiver, _arm_frame(sender)) is Signature.VALID
    unsigned = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    assert check_signature(receiver, _arm_frame(unsigned)) is Signature.UNSIGNED


# ------------------------------------------------------------------------ MAVSDK and the relay


@contextlib.contextmanager
def _signing_sitl(key: bytes) -> Iterator[Sitl]:
    s = load_scenario(sitl_scenarios()["field-5-tags"])
    scenario = dataclasses.replace(s, vehicle=dataclasses.replace(
        s.vehicle, armable_after_s=1.0, height_error_m=0.0))  # it climbs to the true altitude
    sitl = Sitl(scenario, speedup=SPEEDUP, mavlink_port=free_udp_port(), signing_key=key)
    sitl.start()
    try:
        yield sitl
    finally:
        sitl.stop()


async def _first(stream: AsyncIterator[Any], done: Callable[[Any], bool],
                 timeout_s: float = 15.0) -> Any:
    async def first() -> Any:
        async with contextlib.aclosing(stream) as values:  # type: ignore[type-var]
            async for value in values:
                if done(value):
                    return value
        raise AssertionError("stream ended")

    return await asyncio.wait_for(first(), timeout_s)


def test_mavsdk_through_the_relay_flies_the_signing_autopilot(key: bytes) -> None:
    with _signing_sitl(key) as sitl, SigningRelay(sitl.mavlink_url, key) as relay:
        assert relay.mavsdk_url == f"udpout://127.0.0.1:{relay.mavsdk_port}"

        async def flight() -> None:
            async with MavsdkLink.connect(relay.mavsdk_url, timeout_s=10.0) as link:
                await _first(link.telemetry.subscribe_health(),
                             lambda h: h.is_armable and h.is_global_position_ok)
                await link.arm()
                await link.take_off(4.0)
                await _first(link.telemetry.subscribe_position(),
                             lambda p: p.relative_altitude_m > 3.7)

        asyncio.run(flight())
        snap = sitl.autopilot.snapshot()
        assert snap.armed and -snap.vehicle.position_ned[2] > 3.7
        assert (snap.rejected_unsigned, snap.rejected_bad_signature) == (0, 0)
        c = relay.counters
        assert c.to_vehicle > 5 and c.to_mavsdk > 50
        assert (c.dropped_unsigned, c.dropped_bad_signature, c.dropped_malformed) == (0, 0, 0)


def test_mavsdk_without_the_relay_cannot_command_the_signing_autopilot(key: bytes) -> None:
    with _signing_sitl(key) as sitl:

        async def attempt() -> None:
            config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
            async with Mavsdk(config) as mavsdk:
                await mavsdk.add_any_connection(sitl.mavlink_url)
                system = await mavsdk.first_autopilot(timeout_s=10.0)
                assert system is not None  # it hears the autopilot: MAVSDK skips signatures
                await _first(TelemetryAsync(system).subscribe_health(),
                             lambda h: h.is_armable)
                with pytest.raises(ActionError) as refused:
                    await ActionAsync(system).arm()
                assert refused.value.result == ActionResult.TIMEOUT

        asyncio.run(attempt())
        snap = sitl.autopilot.snapshot()
        assert not snap.armed and snap.rejected_unsigned >= 3  # the arm and its retries


class _Peer:
    """A plain UDP socket that speaks MAVLink: MAVSDK's stand-in, or a third party."""

    def __init__(self, mav: mavlink.MAVLink | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.mav = mav or mavlink.MAVLink(None, srcSystem=245, srcComponent=190)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True

    def send(self, msg: mavlink.MAVLink_message, address: tuple[str, int],
             mav: mavlink.MAVLink | None = None) -> None:
        self.sock.sendto(msg.pack(mav or self.mav), address)

    def receive(self) -> list[mavlink.MAVLink_message]:
        try:
            data = self.sock.recv(65535)
        except TimeoutError:
            return []
        return self.parser.parse_buffer(data) or []

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def peers() -> Iterator[Callable[..., _Peer]]:
    made: list[_Peer] = []

    def make(mav: mavlink.MAVLink | None = None) -> _Peer:
        made.append(_Peer(mav))
        return made[-1]

    yield make
    for peer in made:
        peer.close()


def _statustext(mav: mavlink.MAVLink, text: str) -> mavlink.MAVLink_message:
    return mav.statustext_encode(mavlink.MAV_SEVERITY_CRITICAL, text.encode())


def test_injection_on_either_side_of_the_relay_is_dropped(
        key: bytes, peers: Callable[..., _Peer]) -> None:
    port = free_udp_port()
    with _autopilot(port, key) as autopilot, \
            SigningRelay(f"udpin://127.0.0.1:{port}", key) as relay:
        mavsdk, intruder = peers(), peers(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
        mavsdk_side = ("127.0.0.1", relay.mavsdk_port)
        mavsdk.send(mavsdk.mav.heartbeat_encode(18, 8, 0, 0, 4), mavsdk_side)  # MAVSDK is there
        _until(lambda: relay.counters.to_mavsdk > 0)
        # The intruder poses as the autopilot towards MAVSDK, unsigned and with a wrong key.
        forger = new_signer(secrets.token_bytes(32), 1, 1)
        intruder.send(_statustext(intruder.mav, "unsigned intruder"), ("127.0.0.1", port))
        intruder.send(_statustext(forger, "forged intruder"), ("127.0.0.1", port), forger)
        # And arms through the relay's MAVSDK port, which MAVSDK already holds.
        intruder.send(mavsdk.mav.command_long_encode(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0),
                      mavsdk_side)
        _until(lambda: (relay.counters.dropped_unsigned, relay.counters.dropped_bad_signature,
                        relay.counters.dropped_foreign) == (1, 1, 1))
        received = _receive_until(  # the autopilot still comes through
            mavsdk.receive, lambda got: [m.get_type() for m in got].count("HEARTBEAT") >= 2)
        assert all(is_signed(m.get_msgbuf()) for m in received)
        assert "STATUSTEXT" not in [m.get_type() for m in received]
        snap = autopilot.snapshot()
        assert not snap.armed and (snap.rejected_unsigned, snap.rejected_bad_signature) == (0, 0)
        # MAVSDK's own command goes through, signed.
        mavsdk.send(mavsdk.mav.command_long_encode(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0),
                    mavsdk_side)
        _until(lambda: autopilot.snapshot().armed)


def test_relay_over_a_serial_line(key: bytes, peers: Callable[..., _Peer]) -> None:
    """serial:// through a pseudo-terminal: frames split across writes, both directions."""
    master, slave = os.openpty()
    try:
        with SigningRelay(f"serial://{os.ttyname(slave)}:115200", key) as relay:
            mavsdk = peers()
            mavsdk.send(mavsdk.mav.heartbeat_encode(18, 8, 0, 0, 4),
                        ("127.0.0.1", relay.mavsdk_port))
            # To the vehicle: MAVSDK's heartbeat, now signed, on the wire.
            wire = mavlink.MAVLink(None)

            def read_wire() -> list[mavlink.MAVLink_message]:
                if not select.select([master], [], [], 0.05)[0]:
                    return []
                return wire.parse_buffer(os.read(master, 4096)) or []

            got = _receive_until(read_wire, bool)
            assert [m.get_type() for m in got] == ["HEARTBEAT"]
            assert (got[0].get_srcSystem(), got[0].get_srcComponent()) == (245, 190)
            assert check_signature(new_signer(key), got[0].get_msgbuf()) is Signature.VALID
            # From the vehicle: a signed frame in two writes, and an unsigned one.
            autopilot = new_signer(key, 1, 1)
            frame = bytes(_statustext(autopilot, "from the autopilot").pack(autopilot))
            os.write(master, frame[:7])
            os.write(master, frame[7:])
            plain = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            os.write(master, bytes(_statustext(plain, "unsigned").pack(plain)))
            _until(lambda: relay.counters.dropped_unsigned == 1)
            texts = [m.text for m in mavsdk.receive() if m.get_type() == "STATUSTEXT"]
            assert texts == ["from the autopilot"]
            assert relay.counters.to_mavsdk == 1
    finally:
        os.close(master)
        os.close(slave)


def test_relay_lifecycle_and_urls(key: bytes) -> None:
    relay = SigningRelay(f"udp://127.0.0.1:{free_udp_port()}", key)  # udp:// is udpin://
    url = relay.start()
    try:
        assert url.startswith("udpout://127.0.0.1:") and relay.start() == url
        assert relay.counters == RelayCounters()
    finally:
        relay.stop()
    relay.stop()  # idempotent
    assert relay.mavsdk_port == 0
    assert "signing-relay" not in [t.name for t in threading.enumerate()]
    for bad in ("tcpout://127.0.0.1:5760", "udpin://127.0.0.1", "serial:///dev/ttyS0",
                "udpin://127.0.0.1:70000"):
        with pytest.raises(ConfigError) as refused:
            SigningRelay(bad, key)
        assert refused.value.key == "vehicle.connection"
    with pytest.raises(ConfigError, match="cannot open"):
        SigningRelay("serial:///dev/no-such-tty:57600", key).start()
    with pytest.raises(ValueError, match="32 bytes"):
        SigningRelay("udpin://127.0.0.1:14540", key[:16])


# ---------------------------------------------------------------------------------- key files


def _key_file(tmp_path: Path, text: str, mode: int = 0o600) -> Path:
    path = tmp_path / "signing.key"
    path.write_text(text)
    path.chmod(mode)
    return path


def test_a_private_key_file_loads(tmp_path: Path, key: bytes) -> None:
    assert load_signing_key(_key_file(tmp_path, key.hex() + "\n")) == key
    assert load_signing_key(_key_file(tmp_path, key.hex().upper(), 0o400)) == key


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o606, 0o620, 0o602])
def test_a_key_file_others_can_read_or_write_is_refused(tmp_path: Path, key: bytes,
                                                        mode: int) -> None:
    with pytest.raises(ConfigError) as refused:
        load_signing_key(_key_file(tmp_path, key.hex(), mode))
    assert refused.value.key == "vehicle.signing_key_file"
    assert f"mode {mode:04o} lets group or others read or write" in str(refused.value)
    assert "chmod 600" in str(refused.value)


@pytest.mark.parametrize(("text", "why"), [
    ("ab" * 31, "holds a 31-byte key; a MAVLink signing key has 32 bytes"),
    ("ab" * 33, "holds a 33-byte key"),
    ("not hex at all", "must hold 64 hexadecimal digits"),
    ("00" * 32, "all-zero key"),
])
def test_a_malformed_key_is_refused(tmp_path: Path, text: str, why: str) -> None:
    with pytest.raises(ConfigError, match=why) as refused:
        load_signing_key(_key_file(tmp_path, text))
    assert refused.value.key == "vehicle.signing_key_file"


def test_missing_files_symlinks_and_directories_are_refused(tmp_path: Path, key: bytes) -> None:
    target = _key_file(tmp_path, key.hex())
    link = tmp_path / "link.key"
    link.symlink_to(target)
    for path, why in ((tmp_path / "absent.key", "no such file"),
                      (link, "is a symbolic link"), (tmp_path, "not a regular file")):
        with pytest.raises(ConfigError, match=why) as refused:
            load_signing_key(path)
        assert refused.value.key == "vehicle.signing_key_file"


def test_passphrase_keys_match_mavproxy_and_qgroundcontrol() -> None:
    """Both hash the passphrase with SHA-256 (FIPS 180-2 test vector for 'abc')."""
    assert key_from_passphrase("abc").hex() == (
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad")
