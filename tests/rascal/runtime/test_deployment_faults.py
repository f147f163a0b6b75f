"""``[[faults]]`` in a deployment file: which modules get which rules, and errors naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.faults import FAULTS_ENV, FaultRule, parse_rules
from rascal.runtime.deployment import Deployment, DeploymentError, load_deployment

HEAD = """
[deployment]
bus = "udpm://239.255.1.2:7700?ttl=0"

[hosts.front]
[hosts.back]

[modules.time_service]
host = "back"

[modules.ins]
host = "front"

[modules.health]
host = "back"
"""


def load(tmp_path: Path, faults: str) -> Deployment:
    path = tmp_path / "deploy.toml"
    path.write_text(faults + HEAD)  # first: top-level keys must come before any table
    return load_deployment(path)


def test_rules_reach_their_receivers_with_seeds_mixed_per_module(tmp_path: Path) -> None:
    deployment = load(
        tmp_path,
        """
[[faults]]
channels = "IMU|GPS"
loss_pct = 20
jitter_ms = 20
seed = 3

[[faults]]
modules = ["health"]
from_hosts = ["front"]
delay_ms = 50
""",
    )
    ins, health = deployment.spec("ins"), deployment.spec("health")
    assert ins.faults == (FaultRule(channels="IMU|GPS", loss_pct=20, jitter_ms=20, seed=3 * 0x10000 + 11),)
    assert health.faults[0].seed != ins.faults[0].seed
    assert health.faults[1] == FaultRule(delay_ms=50, sources=(ins.source_id,), seed=health.source_id)
    # What the supervisor hands the module process, which reads it back as the same rules.
    assert parse_rules(health.environment()[FAULTS_ENV]) == health.faults
    expected = "channels=IMU|GPS,loss_pct=20,jitter_ms=20,seed=196609"  # 3 * 65536 + 1
    assert deployment.spec("time_service").environment() == {FAULTS_ENV: expected}


def test_to_hosts_and_a_single_table(tmp_path: Path) -> None:
    deployment = load(tmp_path, '[faults]\nto_hosts = ["back"]\nduplicate_pct = 5\n')
    assert not deployment.spec("ins").faults and not deployment.spec("ins").environment()
    assert deployment.spec("health").faults[0].duplicate_pct == 5


@pytest.mark.parametrize(
    ("faults", "complaint"),
    [
        ("[[faults]]\nloss_pct = 120\n", r"faults\[0\]\.loss_pct: expected 0\.\.100"),
        ("[[faults]]\nloss = 1\n", r"faults\[0\]\.loss: unknown key"),
        ('[[faults]]\nmodules = ["brain"]\n', r"faults\[0\]\.modules: 'brain' is not declared"),
        ('[[faults]]\nfrom_hosts = "front"\n', r"faults\[0\]\.from_hosts: expected a list of names"),
        ("[[faults]]\n[[faults]]\njitter_ms = true\n", r"faults\[1\]\.jitter_ms: expected a number"),
        ('[[faults]]\nchannels = "["\n', r"faults\[0\]\.channels: '\[' is not a regular expression"),
        ("faults = 3\n", r"faults: expected a table or an array of tables"),
    ],
)
def test_bad_fault_tables_name_the_key(tmp_path: Path, faults: str, complaint: str) -> None:
    with pytest.raises(DeploymentError, match=complaint):
        load(tmp_path, faults)


def test_a_sender_host_without_modules_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match=r"faults\[0\]\.from_hosts: no modules run on \['spare'\]"):
        load(tmp_path, '[[faults]]\nfrom_hosts = ["spare"]\nloss_pct = 5\n[hosts.spare]\n')
