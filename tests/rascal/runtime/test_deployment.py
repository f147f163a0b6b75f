"""Deployment files: the default loads; every kind of mistake names the file and the key."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from rascal.runtime.deployment import DEFAULT_DEPLOYMENT, DeploymentError, load_deployment

GOOD = """
[deployment]
name = "two"
bus = "udpm://239.255.1.2:7700?ttl=0"
course = "course.rddf"

[hosts.front]
address = "10.0.0.1"
[hosts.back]

[modules.time_service]
host = "back"

[modules.ins]
host = "front"
nice = 5
cpu_budget_pct = 9
set = { filter = "ukf" }

[modules.health]
host = "back"
set = { watch = ["IMU:0.5", "GPS:1.0"] }
"""


def write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "course.rddf").write_text("1,35.0,-117.0,30,10\n2,35.0,-116.99,30,10\n")
    path = tmp_path / "deploy.toml"
    path.write_text(text)
    return path


def test_the_default_deployment_runs_every_module_here() -> None:
    deployment = load_deployment(DEFAULT_DEPLOYMENT)
    assert set(deployment.hosts) == {"localhost"}
    labels = [spec.label for spec in deployment.on_host("localhost")]
    assert labels[0] == "time_service" and {"sim", "ins", "lidar_h_left"} <= set(labels)
    assert len({spec.source_id for spec in deployment.modules}) == len(deployment.modules)


def test_hosts_shared_settings_and_overrides(tmp_path: Path) -> None:
    deployment = load_deployment(write(tmp_path, GOOD))
    assert [s.label for s in deployment.on_host("front")] == ["ins"]
    ins = deployment.spec("ins")
    assert ins.nice == 5 and ins.source_id == 11
    assert ins.cpu_budget_pct == 9.0 and deployment.spec("health").cpu_budget_pct == 3.0  # set, and the default
    assert ins.settings == {"course": str((tmp_path / "course.rddf").resolve()), "filter": "ukf"}
    assert "course" not in deployment.spec("health").settings  # health has no course setting
    assert deployment.spec("health").arguments()[-1] == "watch=IMU:0.5,GPS:1.0"
    with pytest.raises(DeploymentError, match="no host 'side'"):
        deployment.on_host("side")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace('name = "two"', 'name = "two"\nspeed = 3'), r"deployment\.speed: unknown key"),
        (lambda t: t.replace('bus = "udpm://239.255.1.2:7700?ttl=0"\n', ""), r"deployment\.bus: missing"),
        (lambda t: t.replace('course = "course.rddf"', 'course = "nowhere.rddf"'), r"deployment\.course: .* not exist"),
        (lambda t: t.replace('host = "front"', 'host = "side"'), r"modules\.ins\.host: 'side' is not declared"),
        (lambda t: t.replace('host = "front"\n', ""), r"modules\.ins\.host: missing"),
        (lambda t: t.replace("nice = 5", "nice = 40"), r"modules\.ins\.nice: expected 0\.\.19"),
        (lambda t: t.replace("nice = 5", 'nice = "low"'), r"modules\.ins\.nice: expected an integer"),
        (lambda t: t.replace('filter = "ukf"', "filters = 2"), r"modules\.ins\.set\.filters: unknown key"),
        (
            lambda t: t.replace('[modules.health]\nhost = "back"', '[modules.health]\nhost = "back"\nsource_id = 11'),
            r"modules\.health\.source_id: 11 is already used by ins",
        ),
        (lambda t: t + '\n[modules.radar]\nhost = "back"\n', r"modules\.radar\.module: no module named 'radar'"),
        (
            lambda t: t.replace("[modules.time_service]", "[modules.time_service]\nheartbeat_timeout_s = 0.5"),
            r"heartbeat_timeout_s: must exceed",
        ),
        (lambda t: t.replace("cpu_budget_pct = 9", "cpu_budget_pct = 0"), r"modules\.ins\.cpu_budget_pct: expected"),
        (lambda t: t.replace("cpu_budget_pct = 9", 'cpu_budget_pct = "9"'), r"cpu_budget_pct: expected a number"),
        (lambda t: t.replace("[deployment]", "[deployment\n"), r"not valid TOML"),
    ],
)
def test_mistakes_name_the_key(tmp_path: Path, edit, message: str) -> None:  # type: ignore[no-untyped-def]
    path = write(tmp_path, edit(GOOD))
    with pytest.raises(DeploymentError, match=message) as caught:
        load_deployment(path)
    assert str(path) in str(caught.value)


def test_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DeploymentError, match="not found"):
        load_deployment(tmp_path / "none.toml")


def test_the_three_host_vehicle_deployment_splits_the_stack() -> None:
    deployment = load_deployment(DEFAULT_DEPLOYMENT.parent / "vehicle-3hosts.toml")
    by_host = {host: {spec.label for spec in deployment.on_host(host)} for host in deployment.hosts}
    assert {"esvs", "stereo_camera", "lidar_h_left", "nav_sensors"} <= by_host["sensors"]
    assert {"brain", "ins", "time_service"} <= by_host["brainbox"]
    assert {"control", "sim"} <= by_host["drive"]
    assert sum(len(labels) for labels in by_host.values()) == len(deployment.modules)
    assert "iface=" in deployment.bus


def test_each_host_leaves_through_its_own_address_with_its_own_source_ids() -> None:
    deployment = load_deployment(DEFAULT_DEPLOYMENT.parent / "vehicle-3hosts.toml")
    buses = {host: deployment.bus_on(host) for host in deployment.hosts}
    assert buses["brainbox"] == "udpm://239.255.76.67:7667?ttl=1&iface=10.0.0.2"
    assert buses["drive"].endswith("iface=10.0.0.3")
    ids = {deployment.host_source_id(host, 9) for host in deployment.hosts}
    assert len(ids) == 3 and not ids & {spec.source_id for spec in deployment.modules}


def test_a_bus_that_stays_on_the_host_is_left_alone(tmp_path: Path) -> None:
    deployment = load_deployment(write(tmp_path, GOOD))  # ttl=0; front has an address, back none
    assert deployment.bus_on("front") == deployment.bus_on("back") == "udpm://239.255.1.2:7700?ttl=0"
    offsite = dataclasses.replace(
        deployment, bus="udpm://239.255.1.2:7700?ttl=2&iface=10.0.0.9&peers=10.0.0.7,10.0.0.8"
    )
    assert offsite.bus_on("front") == "udpm://239.255.1.2:7700?ttl=2&iface=10.0.0.1&peers=10.0.0.7,10.0.0.8"
    assert offsite.bus_on("back") == offsite.bus  # no address: the file's iface stands
