from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from companion.config import Config, ConfigError, config_from_dict, config_to_toml, load_config


def test_defaults_round_trip_through_toml() -> None:
    text = config_to_toml()
    assert config_from_dict(tomllib.loads(text)) == Config()
    assert Config().setpoints.rate_hz == 50.0
    assert Config().safety.auto_arm is False
    assert Config().limits.max_message_bytes == 1024 * 1024


def test_empty_file_is_the_default(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("")
    assert load_config(p) == Config()


def test_values_are_read_and_frozen(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[vehicle]\nid = "x9"\n[zenoh]\nconnect = ["tcp/10.0.0.1:7447"]\nmode = "client"\n'
                 '[setpoints]\nrate_hz = 100\n[geofence]\nmin = [-5, -5, -10]\nmax = [5, 5, 0]\n')
    cfg = load_config(p)
    assert cfg.vehicle.id == "x9"
    assert cfg.zenoh.connect == ("tcp/10.0.0.1:7447",)
    assert cfg.setpoints.rate_hz == 100.0
    assert cfg.geofence.min == (-5.0, -5.0, -10.0)
    assert cfg.key("status") == "bezier/x9/status"
    with pytest.raises(AttributeError):
        cfg.vehicle.id = "y"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"vehicle": {"idd": "x"}}, "vehicle.idd"),
        ({"safety": {"auto_arming": True}}, "safety.auto_arming"),
        ({"nonsense": {}}, "nonsense"),
        ({"planner": {"bounds": {"speed": 3}}}, "planner.bounds.speed"),
        ({"setpoints": {"rate_hz": -1}}, "setpoints.rate_hz"),
        ({"setpoints": {"rate_hz": "fast"}}, "setpoints.rate_hz"),
        ({"safety": {"auto_arm": 1}}, "safety.auto_arm"),
        ({"zenoh": {"mode": "router2"}}, "zenoh.mode"),
        ({"geofence": {"min": [0, 0]}}, "geofence.min"),
        ({"geofence": {"min": [0, 0, 0], "max": [1, 1, 0]}}, "geofence.min[2]"),
        ({"zenoh": {"listen": "tcp/1.2.3.4:7447"}}, "zenoh.listen"),
    ],
)
def test_bad_options_name_the_key(table: dict, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(table)
    assert info.value.key == key
    assert key in str(info.value)


def test_print_default_config_cli() -> None:
    out = subprocess.run([sys.executable, "-m", "companion", "--print-default-config"],
                         capture_output=True, text=True, check=True).stdout
    assert config_from_dict(tomllib.loads(out)) == Config()


def test_mavlink_urls() -> None:
    from companion.wire.vehicle import parse_url

    assert parse_url("udpout:127.0.0.1:14540") == ("udpout:127.0.0.1:14540", 57600)
    assert parse_url("tcp:10.0.0.2:5760") == ("tcp:10.0.0.2:5760", 57600)
    assert parse_url("serial:/dev/ttyAMA0:921600") == ("/dev/ttyAMA0", 921600)
    assert parse_url("/dev/ttyACM0:115200") == ("/dev/ttyACM0", 115200)
    assert parse_url("/dev/ttyACM0") == ("/dev/ttyACM0", 57600)
