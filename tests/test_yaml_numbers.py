"""Numbers in a config as a user writes them (issue 41). PyYAML follows YAML 1.1, where
``2e-4`` and ``1.5e3`` are texts; the config loader reads every exponent form as a float (as
YAML 1.2 does), so every float key takes it. The reference's defaults are written as YAML
numbers that read back as themselves, and the simulator page's ``sim:`` example loads."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from can_config import load_config
from can_config.config import SimModelConfig
from can_config.keys import REQUIRED, yaml_keys
from can_config.reference import SECTIONS, yaml_number
from can_config.textfile import load_yaml

from .conftest import REPO

FLOAT_KINDS = ("float", "opt_float")


def read_back(tmp_path: Path, text: str) -> object:
    path = tmp_path / "number.yaml"
    path.write_text(f"value: {text}\n")
    return load_yaml(path, "test file")["value"]


@settings(max_examples=300, deadline=None)
@given(value=st.floats(allow_nan=False, allow_infinity=False, width=64),
       form=st.sampled_from(["{:e}", "{:E}", "{:.3e}", "{:g}", "{!r}", "{:.0e}"]))
def test_every_exponent_form_reads_as_the_number(value: float, form: str) -> None:
    import tempfile

    text = form.format(value)
    with tempfile.TemporaryDirectory() as where:
        assert read_back(Path(where), text) == float(text), text


def test_the_forms_users_write(tmp_path: Path) -> None:
    for text, number in (("2e-4", 2e-4), ("1e3", 1000.0), ("-5E+2", -500.0), ("1.5e3", 1500.0), ("2e-05", 2e-5),
                         (".5e1", 5.0), ("+3e0", 3.0)):
        assert read_back(tmp_path, text) == number, text
    for text in ("1e", "e3", "1.0.0", "v1e3"):  # still texts
        assert read_back(tmp_path, text) == text
    assert read_back(tmp_path, "0x10e3") == 0x10E3  # hex, not an exponent


def test_each_defaults_as_written_in_the_reference_reads_back_as_itself(tmp_path: Path) -> None:
    for _, path, fields, _text in SECTIONS:
        for key, field in fields.items():
            if isinstance(field.default, bool) or not isinstance(field.default, (int, float)) or field.default is REQUIRED:
                continue
            written = yaml_number(field.default)
            assert read_back(tmp_path, written) == field.default, f"{path}.{key}: {written}"


def test_every_float_key_of_a_simulated_motor_takes_exponent_notation(tmp_path: Path) -> None:
    floats = {name: (attr, f) for name, (attr, f) in yaml_keys(SimModelConfig).items()
              if f.kind in FLOAT_KINDS and f.low is not None and f.high is not None}
    assert len(floats) >= 5
    written = {name: f"{(f.low + f.high) / 2:e}" for name, (_, f) in floats.items()}  # type: ignore[operator]
    config_path = tmp_path / "rover.yaml"
    config_path.write_text("buses: [{name: can0, interface: socketcand, channel: can0}]\ndrives:\n"
                           "  - {name: motor, node_id: 1, sim: {" + ", ".join(f"{k}: {v}" for k, v in written.items()) + "}}\n")
    model = load_config(config_path).drives[0].sim
    for name, (attr, field) in floats.items():
        assert getattr(model, attr) * field.scale == pytest.approx(float(written[name])), name


def test_the_simulator_pages_sim_example_loads(tmp_path: Path) -> None:
    page = (REPO / "docs" / "simulator.md").read_text()
    block = re.search(r"```yaml\n(.*?)```", page, re.DOTALL)
    assert block is not None and "sim:" in block.group(1)
    drive = yaml.safe_load(block.group(1))[0]
    config_path = tmp_path / "rover.yaml"
    config_path.write_text("buses: [{name: can0, interface: socketcand, channel: can0}]\ndrives:\n"
                           + "\n".join("  " + line for line in block.group(1).splitlines()) + "\n")
    config = load_config(config_path)
    assert config.drives[0].sim.inertia_kg_m2 == 2e-4 and drive["name"] == config.drives[0].name
