"""Command authority in a deployment: the [authority] table and its defaults, and the module key
files the supervisor writes for the processes it starts."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from protocol import channels
from protocol.auth import Keyring, load_keyring
from protocol.authority import OPERATOR_SOURCE_ID
from protocol.signing import derive_seed
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.deployment import DEFAULT_DEPLOYMENT, DeploymentError, load_deployment
from rascal.runtime.module import Runtime
from rascal.supervisor import SUPERVISOR_SOURCE_ID, Supervisor

SMALL = """
[deployment]
bus = "udpm://239.255.1.2:7700?ttl=0"

[modules.time_service]

[modules.ctl]
module = "control"

[modules.lidar_h_left]
module = "lidar"
source_id = 21
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "deploy.toml"
    path.write_text(text)
    return path


def test_the_default_authority_follows_the_modules_that_publish(tmp_path: Path) -> None:
    assert load_deployment(DEFAULT_DEPLOYMENT).authority == {
        channels.ACTUATOR_COMMAND: (40,),
        channels.PATH: (30,),
        channels.STOP: (SUPERVISOR_SOURCE_ID, OPERATOR_SOURCE_ID),
        channels.CONFIG: (SUPERVISOR_SOURCE_ID, OPERATOR_SOURCE_ID),
        channels.TIME_SYNC: (1,),
    }
    three = load_deployment(DEFAULT_DEPLOYMENT.parent / "vehicle-3hosts.toml").authority
    assert three[channels.STOP] == (9, 109, 209, OPERATOR_SOURCE_ID)  # every host's supervisor
    small = load_deployment(write(tmp_path, SMALL)).authority
    assert small[channels.ACTUATOR_COMMAND] == (40,)  # by package: labelled "ctl"
    assert small[channels.PATH] == (30,)  # no brain here: one started by hand, at its default id
    no_master = load_deployment(write(tmp_path, SMALL.replace("[modules.time_service]\n", ""))).authority
    assert no_master[channels.TIME_SYNC] == (1,)  # the time service run by hand is still trusted


def test_an_authority_table_names_labels_words_and_ids(tmp_path: Path) -> None:
    text = SMALL + '[authority]\nACTUATOR_COMMAND = ["ctl", "operator"]\nSTOP = ["lidar_h_left", 4242]\nPATH = []\n'
    authority = load_deployment(write(tmp_path, text)).authority
    assert authority[channels.ACTUATOR_COMMAND] == (40, OPERATOR_SOURCE_ID)
    assert authority[channels.STOP] == (21, 4242)
    assert authority[channels.PATH] == ()
    assert authority[channels.TIME_SYNC] == (1,)  # unnamed: its default


@pytest.mark.parametrize(
    "table,key,words",
    [
        ('IMU = ["ctl"]', "authority.IMU", "not a governed channel"),
        ('STOP = ["brain"]', "authority.STOP", "'brain' is no module label"),
        ("STOP = [0]", "authority.STOP", "0 is no module label"),
        ('STOP = "operator"', "authority.STOP", "expected a list"),
    ],
)
def test_a_wrong_authority_entry_names_the_field(tmp_path: Path, table: str, key: str, words: str) -> None:
    with pytest.raises(DeploymentError) as caught:
        load_deployment(write(tmp_path, f"{SMALL}[authority]\n{table}\n"))
    assert key in str(caught.value) and words in str(caught.value)


def supervisor(tmp_path: Path, keyring: Keyring) -> Supervisor:
    deployment = load_deployment(write(tmp_path, SMALL))
    bus = Bus(MemTransport(f"authority-supervisor-{id(tmp_path)}"), SUPERVISOR_SOURCE_ID, keyring, MasterClock())
    return Supervisor(Runtime(bus, MasterClock()), deployment, "localhost", tmp_path / "run")


def test_the_supervisor_writes_each_module_its_own_private_key_file(tmp_path: Path) -> None:
    master = Keyring.generate()
    sup = supervisor(tmp_path, master)
    lidar = sup.deployment.spec("lidar_h_left")
    path = sup.module_key_file(lidar)
    assert path is not None and path.parent == tmp_path / "run" / "keys"
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600 and stat.S_IMODE(os.stat(path.parent).st_mode) == 0o700
    text = path.read_text()
    assert master.signing_master.hex() not in text  # type: ignore[union-attr]
    assert derive_seed(master.signing_master, 40).hex() not in text  # type: ignore[arg-type]
    ring = load_keyring(path)
    assert ring.source_id == 21 and ring.keys == master.keys
    assert ring.authority is not None and dict(ring.authority.table) == {
        channel: frozenset(ids) for channel, ids in sup.deployment.authority.items()
    }
    assert sup.module_key_file(lidar) == path  # written once, kept across restarts
    sup.on_stop()
    assert not path.parent.exists()  # the keys do not outlive the run


def test_a_legacy_key_file_gives_no_module_key_files(tmp_path: Path) -> None:
    sup = supervisor(tmp_path, Keyring({1: bytes(32)}, 1))
    assert sup.module_key_file(sup.deployment.spec("ctl")) is None  # children get the master file, as before
