"""Command authority: per-source signing keys derived from the master, module key files that hold
one source's key only, the SIGNATURE flag on the wire, and receivers that reject a governed
message without a valid signature by a source with authority (counted as ``unauthorized``)."""

from __future__ import annotations

import hashlib
import itertools
import os
import stat
import time
from pathlib import Path
from typing import Any

import pytest

from protocol import channels
from protocol import messages as m
from protocol.auth import KeyFileError, Keyring, load_keyring, write_keyring
from protocol.authority import GOVERNED_CHANNELS, OPERATOR_SOURCE_ID, Authority, needs_signature
from protocol.codec import FLAG_SIGNATURE, FLAG_SIGNED, Codec, body_span, signed_part
from protocol.errors import ProtocolError, Reason
from protocol.signing import SIGNATURE_BYTES, Signed, Signer, Verifier, derive_seed, public_key_of
from protocol.transport import MemTransport, open_transport
from rascal.logplay import restamp
from rascal.logread import Datagram, decode
from rascal.operator_stop import order_source_id
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock, SharedClock
from rascal.runtime.timeclient import MIN_REQUEST_PERIOD_NS, TimeClient, TimeMaster
from tests.protocol.wire_samples import T0_NS

CONTROL, LIDAR, TIME_SERVICE, SIM, SUPERVISOR = 40, 21, 1, 5, 9
TABLE = {
    channels.ACTUATOR_COMMAND: [CONTROL],
    channels.PATH: [30],
    channels.STOP: [OPERATOR_SOURCE_ID, SUPERVISOR],
    channels.CONFIG: [OPERATOR_SOURCE_ID, SUPERVISOR],
    channels.TIME_SYNC: [TIME_SERVICE],
}
COMMAND = m.ActuatorCommand(0.4, 0.0, 0.05, "")
_hubs = itertools.count()


def master() -> Keyring:
    return Keyring({1: bytes(range(32))}, 1, bytes(range(32, 64)))


def module_keyring(source_id: int, ring: Keyring | None = None) -> Keyring:
    ring = ring or master()
    return ring.for_module(source_id, Authority.derive(TABLE, ring.signing_master))  # type: ignore[arg-type]


# -- keys -----------------------------------------------------------------------------------------


def test_the_kdf_is_keyed_blake2b_of_the_source_id_and_deterministic() -> None:
    signing_master = bytes(range(32, 64))
    seed = derive_seed(signing_master, 7)
    expected = hashlib.blake2b(b"\x07\x00", key=signing_master, person=b"rascal-ed25519", digest_size=32).digest()
    assert seed == expected == derive_seed(signing_master, 7)
    assert seed.hex() == "498244be7b41f9881218f566cefc72e933e4eee755d518b50ee19f201c2395fa"  # SPEC.md section 14
    seeds = {derive_seed(signing_master, sid) for sid in range(1, 2000)}
    assert len(seeds) == 1999  # one per source
    assert derive_seed(bytes(32), 7) != seed  # and per master
    assert Signer(7, seed).public_key == public_key_of(signing_master, 7)
    with pytest.raises(ValueError):
        derive_seed(signing_master, 0)


def test_a_signature_verifies_only_for_its_source_and_bytes() -> None:
    signer = Signer(CONTROL, derive_seed(master().signing_master, CONTROL))  # type: ignore[arg-type]
    data = b"header, channel and body"
    signature = signer.sign(data)
    assert len(signature) == SIGNATURE_BYTES
    assert Verifier(signer.public_key).verify(Signed(data, signature))
    assert not Verifier(signer.public_key).verify(Signed(data + b"!", signature))
    assert not Verifier(public_key_of(master().signing_master, LIDAR)).verify(Signed(data, signature))  # type: ignore[arg-type]
    assert repr(signer) == f"Signer(source_id={CONTROL})"


def test_a_module_key_file_holds_its_own_key_and_no_other_secret(tmp_path: Path) -> None:
    ring = master()
    path = tmp_path / "lidar.key"
    write_keyring(path, module_keyring(LIDAR, ring))
    text = path.read_text()
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert ring.signing_master.hex() not in text  # type: ignore[union-attr]
    assert derive_seed(ring.signing_master, LIDAR).hex() in text  # type: ignore[arg-type]
    others = {sid for sources in TABLE.values() for sid in sources} | set(range(1, 100)) - {LIDAR}
    assert not any(derive_seed(ring.signing_master, sid).hex() in text for sid in others)  # type: ignore[arg-type]
    loaded = load_keyring(path)
    assert loaded == module_keyring(LIDAR, ring)
    assert loaded.signing_master is None and loaded.source_id == LIDAR and not loaded.legacy
    assert loaded.authority is not None and loaded.authority.table[channels.ACTUATOR_COMMAND] == {CONTROL}
    assert loaded.signer(LIDAR) is not None and loaded.signer(CONTROL) is None
    assert repr(loaded) == f"Keyring(key_ids=[1], active=1, module source_id={LIDAR})"
    assert repr(ring) == "Keyring(key_ids=[1], active=1, signing master)"


def test_keygen_and_a_master_file_round_trip_with_the_signing_master(tmp_path: Path) -> None:
    ring = Keyring.generate()
    assert ring.signing_master is not None and len(ring.signing_master) == 32
    write_keyring(tmp_path / "bus.key", ring)
    assert load_keyring(tmp_path / "bus.key") == ring
    assert ring.signer(1234) is not None  # the master signs as anyone


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(0o600)
    return path


MODULE_FILE = (
    'active = 1\nsource_id = 21\nsigning_seed = "{seed}"\n[keys]\n1 = "{key}"\n'
    '[public]\n40 = "{public}"\n[authority]\nACTUATOR_COMMAND = [40]\n'
)
HEX = "ab" * 32


@pytest.mark.parametrize(
    "text,entry",
    [
        (f'signing_master = "{HEX[:-2]}"\n[keys]\n1 = "{HEX}"\n', "signing_master"),
        (f'signing_master = "{HEX}"\nsource_id = 21\n[keys]\n1 = "{HEX}"\n', "signing_master"),
        (f'source_id = 21\n[keys]\n1 = "{HEX}"\n', "signing_seed"),
        (MODULE_FILE.format(seed=HEX, key=HEX, public=HEX).replace("source_id = 21", "source_id = 0"), "source_id"),
        (MODULE_FILE.format(seed=HEX[:8], key=HEX, public=HEX), "signing_seed"),
        (MODULE_FILE.format(seed=HEX, key=HEX, public=HEX).replace("ACTUATOR_COMMAND", "IMU"), "authority.IMU"),
        (MODULE_FILE.format(seed=HEX, key=HEX, public=HEX).replace("[40]", "[41]"), "authority.ACTUATOR_COMMAND"),
        (MODULE_FILE.format(seed=HEX, key=HEX, public=HEX).replace("[40]", '["control"]'), "authority.ACTUATOR"),
        (MODULE_FILE.format(seed=HEX, key=HEX, public=HEX[:10]), "public.40"),
    ],
    ids=[
        "short master",
        "master with module entries",
        "module entries missing",
        "source id zero",
        "short seed",
        "ungoverned channel",
        "no public key",
        "label not id",
        "short public key",
    ],
)
def test_a_malformed_signing_entry_names_the_file_and_entry(tmp_path: Path, text: str, entry: str) -> None:
    path = _write(tmp_path / "bus.key", text)
    with pytest.raises(KeyFileError) as caught:
        load_keyring(path)
    assert str(path) in str(caught.value) and entry in str(caught.value)


def test_a_module_key_file_is_refused_when_others_can_read_it(tmp_path: Path) -> None:
    path = tmp_path / "lidar.key"
    write_keyring(path, module_keyring(LIDAR))
    path.chmod(0o640)
    with pytest.raises(KeyFileError, match="chmod 600"):
        load_keyring(path)


def test_only_the_master_derives_module_keys() -> None:
    with pytest.raises(KeyFileError):
        Keyring({1: bytes(32)}, 1).for_module(LIDAR, Authority.derive(TABLE, bytes(32)))
    with pytest.raises(KeyFileError):
        Keyring({1: bytes(32)}, 1, bytes(32), source_id=LIDAR)  # a master is not a module keyring


def test_which_messages_are_signed() -> None:
    assert needs_signature(channels.ACTUATOR_COMMAND, COMMAND)
    assert needs_signature(channels.STOP, m.StopCommand(2, ""))
    assert needs_signature(channels.TIME_SYNC, m.TimeSync(m.TimeSyncKind.REPLY, 5, 1, 2, 3))
    assert not needs_signature(channels.TIME_SYNC, m.TimeSync(m.TimeSyncKind.REQUEST, 5, 1))
    assert not needs_signature(channels.IMU, m.ImuSample(0, 0, 0, 0, 0, 0))
    assert set(GOVERNED_CHANNELS) == set(TABLE)


def test_the_operator_tools_sign_as_the_operator_with_the_master_file() -> None:
    assert order_source_id(master()) == OPERATOR_SOURCE_ID
    assert order_source_id(module_keyring(SUPERVISOR)) == SUPERVISOR
    assert order_source_id(Keyring({1: bytes(32)}, 1)) is None  # legacy: a random tool id


# -- the wire -------------------------------------------------------------------------------------


def test_the_signature_flag_round_trips_through_the_codec() -> None:
    ring = master()
    codec = Codec(ring)
    signer = ring.signer(CONTROL)
    data = codec.encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 1, T0_NS, T0_NS, signer)
    plain = codec.encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 1, T0_NS, T0_NS)
    assert data[3] == FLAG_SIGNED | FLAG_SIGNATURE and len(data) == len(plain) + SIGNATURE_BYTES
    opened = codec.open(data)
    assert bytes(opened.body) == bytes(codec.open(plain).body)
    signed = signed_part(data)
    covered = plain[:3] + bytes([FLAG_SIGNED | FLAG_SIGNATURE]) + plain[4:-16]  # header with the flag set
    assert signed is not None and bytes(signed.data) == covered
    assert Verifier(signer.public_key).verify(signed)  # type: ignore[union-attr]
    assert body_span(data) == body_span(plain)
    assert signed_part(plain) is None
    with pytest.raises(ValueError):
        Codec(None).encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 1, T0_NS, T0_NS, signer)


def test_an_older_receivers_flags_check_refuses_a_signature() -> None:
    """What a receiver of the previous format does: flags beyond SIGNED are bad_header. Here, a
    signature flag without SIGNED is bad_header too."""
    ring = master()
    data = bytearray(Codec(ring).encode(b"STOP", m.StopCommand(1, ""), 9, 1, T0_NS, T0_NS, ring.signer(9)))
    data[3] = FLAG_SIGNATURE
    with pytest.raises(ProtocolError) as caught:
        Codec(None).open(bytes(data))
    assert caught.value.reason is Reason.BAD_HEADER


# -- receivers ------------------------------------------------------------------------------------


class Net:
    """A private in-process hub with one manual clock, a receiving node that enforces authority
    (a module key file, as the supervisor gives sim), and a raw tap to inject datagrams."""

    def __init__(self, *, python_only: bool = False) -> None:
        self.url = f"mem://authority-{next(_hubs)}"
        self.clock = ManualClock(T0_NS)
        self.receiver = Bus(open_transport(self.url), SIM, module_keyring(SIM), self.clock)
        if python_only:
            self.receiver._receiver = None  # the C Receiver's twin, Bus._accept, alone
        self.heard: list[tuple[str, int, Any]] = []
        for channel in (channels.ACTUATOR_COMMAND, channels.STOP, channels.IMU):
            self.receiver.subscribe(channel, lambda msg, env: self.heard.append((env.channel, env.source_id, msg)))
        tap = open_transport(self.url)
        assert isinstance(tap, MemTransport)
        self.tap = tap
        self.seq = itertools.count(1)

    def node(self, source_id: int, keyring: Keyring) -> Bus:
        return Bus(open_transport(self.url), source_id, keyring, self.clock)

    def forge(self, channel: str, msg: Any, source_id: int, keyring: Keyring, signer: Signer | None) -> None:
        """What any MAC-key holder can send: any source id, a signature of its choosing or none."""
        data = Codec(keyring).encode(channel.encode(), msg, source_id, next(self.seq), T0_NS, T0_NS, signer)
        self.tap.send(channel, data)

    def deliver(self) -> list[tuple[str, int, Any]]:
        self.receiver.poll()
        heard, self.heard = self.heard, []
        return heard

    def rejects(self) -> dict[tuple[int | None, str], int]:
        return dict(self.receiver.rejects)


@pytest.fixture(params=["c", "python"])
def net(request: pytest.FixtureRequest) -> Net:
    return Net(python_only=request.param == "python")


def test_a_command_signed_by_the_source_with_authority_is_accepted(net: Net) -> None:
    control = net.node(CONTROL, module_keyring(CONTROL))
    control.publish(channels.ACTUATOR_COMMAND, COMMAND)
    assert net.deliver() == [(channels.ACTUATOR_COMMAND, CONTROL, COMMAND)]
    operator = net.node(OPERATOR_SOURCE_ID, master())  # the master signs as the operator
    operator.publish(channels.STOP, m.StopCommand(2, "e-stop"))
    assert net.deliver() == [(channels.STOP, OPERATOR_SOURCE_ID, m.StopCommand(2, "e-stop"))]
    assert not net.rejects()


def test_forged_commands_are_rejected_as_unauthorized_and_counted(net: Net) -> None:
    lidar = module_keyring(LIDAR)  # all a compromised lidar holds
    own = lidar.signer(LIDAR)
    net.forge(channels.ACTUATOR_COMMAND, COMMAND, CONTROL, lidar, None)  # no signature
    net.forge(channels.ACTUATOR_COMMAND, COMMAND, CONTROL, lidar, own)  # signed, but not by control
    net.forge(channels.ACTUATOR_COMMAND, COMMAND, LIDAR, lidar, own)  # its own, without authority
    net.forge(channels.STOP, m.StopCommand(2, "forged"), OPERATOR_SOURCE_ID, lidar, own)
    net.forge(channels.STOP, m.StopCommand(2, "forged"), LIDAR, lidar, own)
    assert net.deliver() == []
    assert net.rejects() == {
        (CONTROL, "unauthorized"): 2,
        (LIDAR, "unauthorized"): 2,
        (OPERATOR_SOURCE_ID, "unauthorized"): 1,
    }
    # Its own channels still work: the MAC is the only gate there (docs/SECURITY.md).
    net.forge(channels.IMU, m.ImuSample(0, 0, 9.8, 0, 0, 0), LIDAR, lidar, None)
    assert [source for _channel, source, _msg in net.deliver()] == [LIDAR]


def test_a_tampered_signature_is_unauthorized_even_with_a_valid_tag(net: Net) -> None:
    ring = master()
    data = bytearray(Codec(ring).encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 7, T0_NS, T0_NS, ring.signer(CONTROL)))
    data[-20] ^= 0x01  # inside the signature
    tagged = bytes(data[:-16]) + ring.sign(bytes(data[:-16]))  # a MAC-key holder re-tags it
    net.tap.send(channels.ACTUATOR_COMMAND, tagged)
    assert net.deliver() == []
    assert net.rejects() == {(CONTROL, "unauthorized"): 1}


def test_a_forgery_leaves_no_trace_in_its_victims_replay_window(net: Net) -> None:
    """A forged command numbered far ahead is refused before the window sees it, so control's
    next genuine command (numbered below it) is still accepted."""
    lidar = module_keyring(LIDAR)
    data = Codec(lidar).encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 2**62, T0_NS, T0_NS)
    net.tap.send(channels.ACTUATOR_COMMAND, data)
    net.node(CONTROL, module_keyring(CONTROL)).publish(channels.ACTUATOR_COMMAND, COMMAND)
    assert [source for _channel, source, _msg in net.deliver()] == [CONTROL]
    assert net.rejects() == {(CONTROL, "unauthorized"): 1}


def test_a_node_holding_the_master_file_signs_but_enforces_nothing() -> None:
    net = Net()
    trusted = net.node(77, master())
    heard: list[int] = []
    trusted.subscribe(channels.ACTUATOR_COMMAND, lambda _msg, env: heard.append(env.source_id))
    net.forge(channels.ACTUATOR_COMMAND, COMMAND, CONTROL, master(), None)
    trusted.poll()
    assert heard == [CONTROL] and not trusted.rejects


def test_a_module_key_file_cannot_sign_as_another_source() -> None:
    net = Net()
    rogue = net.node(CONTROL, module_keyring(LIDAR))
    with pytest.raises(PermissionError, match="no signing key for source 40"):
        rogue.publish(channels.ACTUATOR_COMMAND, COMMAND)
    rogue.publish(channels.IMU, m.ImuSample(0, 0, 9.8, 0, 0, 0))  # ungoverned: as before


def test_a_legacy_key_file_works_as_before() -> None:
    """No signing_master: no signature on the wire, and a legacy receiver takes the command."""
    legacy = Keyring({1: bytes(range(32))}, 1)
    net = Net()
    sender = net.node(CONTROL, legacy)
    receiver = net.node(SIM + 1, legacy)
    heard: list[int] = []
    receiver.subscribe(channels.ACTUATOR_COMMAND, lambda _msg, env: heard.append(env.source_id))
    capture = open_transport(net.url)
    assert isinstance(capture, MemTransport)
    capture.listen(channels.ACTUATOR_COMMAND)
    sender.publish(channels.ACTUATOR_COMMAND, COMMAND)
    datagrams: list[bytes] = []
    capture.receive(datagrams.append, 0.0, 10)
    assert [d[3] for d in datagrams] == [FLAG_SIGNED]
    receiver.poll()
    assert heard == [CONTROL] and not receiver.rejects


def test_c_and_python_receive_paths_agree_on_governed_traffic() -> None:
    """The same mix of genuine and forged datagrams through a receiver with the C Receiver and
    one with Bus._accept only: the same deliveries and the same rejects."""
    ring, lidar = master(), module_keyring(LIDAR)
    datagrams = []
    for seq in range(1, 41):
        source = (CONTROL, LIDAR, OPERATOR_SOURCE_ID)[seq % 3]
        signer = (ring.signer(source), lidar.signer(LIDAR), None)[seq % 4 % 3]
        channel = (channels.ACTUATOR_COMMAND, channels.STOP, channels.IMU)[seq % 5 % 3]
        msg = {
            channels.ACTUATOR_COMMAND: COMMAND,
            channels.STOP: m.StopCommand(1, ""),
            channels.IMU: m.ImuSample(0, 0, 9.8, 0, 0, seq),
        }[channel]
        datagrams.append((channel, Codec(ring).encode(channel.encode(), msg, source, seq, T0_NS, T0_NS, signer)))
    outcomes = []
    for python_only in (False, True):
        net = Net(python_only=python_only)
        for channel, data in datagrams:
            net.tap.send(channel, data)
        outcomes.append((net.deliver(), net.rejects()))
    assert outcomes[0] == outcomes[1]
    delivered, rejects = outcomes[0]
    assert delivered and rejects and set(reason for _source, reason in rejects) == {"unauthorized"}


# -- time sync ------------------------------------------------------------------------------------


def test_a_client_uses_only_replies_signed_by_the_time_service() -> None:
    """A rogue lidar answers the client's request first, echoing its nonce (it hears every
    request): unsigned as the time service, and signed as itself. Both are refused and counted,
    neither uses up the nonce, and the genuine reply that follows is the one sample taken."""
    url = f"mem://authority-time-{next(_hubs)}"
    master_clock = ManualClock(T0_NS)
    service = Bus(open_transport(url), TIME_SERVICE, module_keyring(TIME_SERVICE), master_clock)
    TimeMaster(service)
    clock = SharedClock()
    client_bus = Bus(open_transport(url), SIM, module_keyring(SIM), clock)
    client = TimeClient(client_bus, clock)
    lidar = module_keyring(LIDAR)
    rogue = Bus(open_transport(url), LIDAR, lidar, master_clock)
    requests: list[m.TimeSync] = []
    rogue.subscribe(channels.TIME_SYNC, lambda msg, _env: requests.append(msg))
    bystander = Bus(open_transport(url), 60, module_keyring(60), clock)
    TimeClient(bystander, clock)

    client.request()
    rogue.poll()
    (request,) = [r for r in requests if r.kind == m.TimeSyncKind.REQUEST]
    steer = m.TimeSync(m.TimeSyncKind.REPLY, SIM, request.t1_local_ns, T0_NS + 10**10, T0_NS + 10**10)
    forged = Codec(lidar).encode(b"TIME_SYNC", steer, TIME_SERVICE, 1, T0_NS, T0_NS)
    rogue.send_raw(channels.TIME_SYNC, forged)  # as the time service, unsigned
    rogue.publish(channels.TIME_SYNC, steer)  # as itself, signed
    service.poll()  # the genuine reply
    client_bus.poll()
    assert client.replies == 1
    assert dict(client_bus.rejects) == {(TIME_SERVICE, "unauthorized"): 1, (LIDAR, "unauthorized"): 1}
    bystander.poll()
    assert not bystander.rejects  # replies to others are not checked at all


def test_a_client_asks_at_most_once_per_ten_ms_however_often_it_is_called() -> None:
    """Each request costs the master a signature: a caller spinning on its own echoed request
    must not flood it (its replies would then come too late for the 32 nonces kept)."""
    url = f"mem://authority-flood-{next(_hubs)}"
    clock = SharedClock()
    client = TimeClient(Bus(open_transport(url), SIM, master(), clock), clock)
    tap = open_transport(url)
    assert isinstance(tap, MemTransport)
    tap.listen(channels.TIME_SYNC)
    start = time.monotonic()
    while time.monotonic() - start < 0.1:
        client.request()
    sent: list[bytes] = []
    tap.receive(sent.append, 0.0, 10_000)
    assert 1 <= len(sent) <= 0.1 / (MIN_REQUEST_PERIOD_NS / 1e9) + 1


# -- recordings -----------------------------------------------------------------------------------


def test_recorded_signed_commands_decode_and_are_signed_anew_when_played() -> None:
    """A recording keeps the signature; its body still decodes, and `rascal log play` signs the
    restamped command anew for its source with the master file (enforcing nodes accept it), or
    drops the signature it can no longer vouch for."""
    ring = master()
    recorded = Codec(ring).encode(b"ACTUATOR_COMMAND", COMMAND, CONTROL, 5, T0_NS, T0_NS, ring.signer(CONTROL))
    assert decode(Datagram(channels.ACTUATOR_COMMAND, CONTROL, 5, T0_NS, T0_NS, T0_NS, 31, recorded)) == COMMAND
    authority = Authority.derive(TABLE, ring.signing_master)  # type: ignore[arg-type]
    played = restamp(recorded, 9, T0_NS + 1, T0_NS + 2, ring)
    opened = Codec(ring).open(played)
    assert (opened.seq, opened.t_pub_ns, played[3]) == (9, T0_NS + 2, FLAG_SIGNED | FLAG_SIGNATURE)
    authority.check(channels.ACTUATOR_COMMAND, CONTROL, signed_part(played))
    lidar = module_keyring(LIDAR)
    unvouched = restamp(recorded, 10, T0_NS, T0_NS, lidar)
    assert unvouched[3] == FLAG_SIGNED and Codec(lidar).open(unvouched).seq == 10
    with pytest.raises(ProtocolError, match="without a signature"):
        authority.check(channels.ACTUATOR_COMMAND, CONTROL, signed_part(unvouched))
