"""Configuration: validation errors name the file, the key, the value and what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from can_config import DEFAULT_CONFIG, ConfigError, EdsError, load_config, load_drive_od, parse_config

from .conftest import SHARED_EDS, requires_shared

GOOD = DEFAULT_CONFIG.read_text()


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rover.yaml"
    path.write_text(text)
    return path


def test_default_config_loads() -> None:
    config = load_config()
    assert config.drives[0].name == "motor"
    assert config.bus("can0").bus_kwargs() == {"interface": "socketcand", "channel": "can0",
                                                "host": "127.0.0.1", "port": 29536, "tcp_tune": True}


def test_socketcand_is_tuned_for_latency_unless_the_config_says_no() -> None:
    """Nagle's algorithm and delayed ACKs hold small frames 20-40 ms: a config without tuning
    keys gets TCP_NODELAY/QUICKACK (python-can's tcp_tune); 'tcp_tune: false' turns it off."""
    bus = {"name": "can0", "interface": "socketcand", "channel": "can0", "kwargs": {"host": "h", "port": 1}}
    drives = [{"name": "a", "node_id": 1}]
    assert parse_config({"buses": [bus], "drives": drives}).buses[0].bus_kwargs()["tcp_tune"] is True
    off = {**bus, "kwargs": {"host": "h", "port": 1, "tcp_tune": False}}
    assert parse_config({"buses": [off], "drives": drives}).buses[0].bus_kwargs()["tcp_tune"] is False
    other = {**bus, "interface": "socketcan"}
    assert "tcp_tune" not in parse_config({"buses": [other], "drives": drives}).buses[0].bus_kwargs()


def test_wrong_type_names_file_key_value_and_allowed(tmp_path: Path) -> None:
    path = write(tmp_path, GOOD.replace("gear_ratio: 1.0", "gear_ratio: fast"))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert str(path) in text and "drives[0].gear_ratio" in text and "'fast'" in text and "expected a number" in text


@pytest.mark.parametrize(("text", "error"), [
    pytest.param(GOOD.replace("gear_ratio:", "gear_ration:"),
                 r"drives\[0\]\.gear_ration: unknown key\. Did you mean 'gear_ratio'\?", id="unknown key, the close one"),
    pytest.param(GOOD.replace("node_id: 1", "node_id: 128"),
                 r"node_id: got 128; expected a value >= 1 and <= 127", id="node id out of range"),
    pytest.param("buses: [\n  - name: can0\n", r"line \d+, column \d+: not valid YAML", id="malformed YAML, its line"),
    pytest.param(GOOD.replace("joint: continuous", "joint: limited\n    min_deg: 10\n    max_deg: -10"),
                 r"min_deg must be below max_deg", id="limited joint, limits out of order"),
    pytest.param(GOOD.replace("name: motor", "name: !!python/object/apply:os.system ['true']"), None,
                 id="YAML never evaluated"),
])
def test_a_bad_config_says_what_is_wrong(tmp_path: Path, text: str, error: str | None) -> None:
    with pytest.raises(ConfigError, match=error):
        load_config(write(tmp_path, text))


def test_missing_eds_is_a_clear_error(tmp_path: Path) -> None:
    path = write(tmp_path, GOOD.replace("eds: generic", "eds: nowhere.eds"))
    config = load_config(path)
    with pytest.raises(EdsError, match=r"nowhere\.eds: EDS file not found"):
        load_drive_od(config.drives[0].eds)


@requires_shared
@pytest.mark.parametrize("eds", sorted(p.name for p in SHARED_EDS.glob("*.eds")) if SHARED_EDS.is_dir() else [])
def test_every_shared_eds_loads(eds: str) -> None:
    if eds == "python_canopen_sample.eds":
        with pytest.raises(EdsError, match="lacks 0x6040"):
            load_drive_od(SHARED_EDS / eds)
    else:
        od = load_drive_od(SHARED_EDS / eds, 7)
        assert 0x6041 in od


def test_unreadable_eds_is_a_clear_error(tmp_path: Path) -> None:
    from can_config.eds import load_od
    eds = tmp_path / "drive.eds"
    eds.write_bytes(b"\x00\xff not an eds \x00")
    with pytest.raises(EdsError, match=r"drive\.eds: (cannot parse the EDS|the EDS holds no objects)"):
        load_od(eds)


def test_drive_namespace_prefixes_its_ros_names(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, GOOD.replace("node_id: 1", "node_id: 1\n    namespace: arm/left")))
    assert config.drives[0].ros_prefix == "arm/left/motor"
    from can_config import config_to_dict, parse_config
    assert parse_config(config_to_dict(config)).drives[0].namespace == "arm/left"


@pytest.mark.parametrize("bad", ["arm//left", "1arm", "arm left", "arm/-x"])
def test_bad_namespace_says_what_a_namespace_is(tmp_path: Path, bad: str) -> None:
    path = write(tmp_path, GOOD.replace("node_id: 1", f"node_id: 1\n    namespace: '{bad}'"))
    with pytest.raises(ConfigError, match=r"drives\[0\]\.namespace: got .*expected a ROS namespace"):
        load_config(path)
