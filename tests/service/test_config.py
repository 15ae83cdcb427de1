"""The plant configuration file and the settings: invalid input is refused with the key path."""

from pathlib import Path

import pytest

from service.config import ConfigError, Settings, load_plant_config

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "plant.yaml"


def test_the_example_plant_file_is_valid():
    plant = load_plant_config(EXAMPLE)
    assert [loop.id for loop in plant.loops] == ["FIC-101", "LIC-102"]
    assert plant.loop("LIC-102").process_type == "integrating"
    assert plant.loop("FIC-101").tags.items() == [
        ("op", "FIC101.OP"), ("pv", "FIC101.PV"), ("sp", "FIC101.SP"), ("mode", "FIC101.MODE")]
    assert plant.loop("FIC-101").mode_map == {16.0: "manual", 8.0: "auto", 4.0: "cascade"}


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n  - id: B\n    tags: {pv: Y}\n",
         "loops[1].ts: Field required"),
        ("loops:\n  - id: A\n    ts: -1\n    tags: {op: X}\n",
         "loops[0].ts: Input should be greater than 0 (got -1)"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {}\n",
         "loops[0].tags: Value error, a loop needs at least an op or a pv tag"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n    ranges: {op: [100, 0]}\n",
         "loops[0].ranges: Value error, range of op must have high > low"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n    unit: nowhere\n",
         "loops[0].unit: unknown unit 'nowhere'"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n  - id: B\n    ts: 1\n"
         "    tags: {op: X}\n", "duplicate tags (a tag belongs to one loop): 'X'"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n    controler: {Kc: 1}\n",
         "loops[0].controler: Extra inputs are not permitted"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X}\n    controller: {Kc: 1}\n",
         "loops[0].controller: Value error, a PI controller needs Ti"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X, mode: M}\n",
         "loops[0]: Value error, a mode tag and a mode_map go together"),
        ("loops:\n  - id: A\n    ts: 1\n    tags: {op: X, mode: M}\n    mode_map: {1: hand}\n",
         "loops[0].mode_map[1]: Input should be 'auto', 'cascade' or 'manual'"),
        ("loops: [\n", "not valid YAML"),
    ],
)
def test_invalid_plant_files_name_the_key_and_the_reason(tmp_path, yaml_text, message):
    path = tmp_path / "plant.yaml"
    path.write_text(yaml_text)
    with pytest.raises(ConfigError) as info:
        load_plant_config(path)
    assert message in str(info.value)
    assert str(path) in str(info.value)


def test_production_refuses_a_default_or_missing_api_key(monkeypatch):
    monkeypatch.setenv("LOOPWATCH_ENVIRONMENT", "production")
    for key in (None, "dev-insecure-key", "short"):
        if key is None:
            monkeypatch.delenv("LOOPWATCH_API_KEY", raising=False)
        else:
            monkeypatch.setenv("LOOPWATCH_API_KEY", key)
        with pytest.raises(ValueError, match="LOOPWATCH_API_KEY must be set"):
            Settings()
    monkeypatch.setenv("LOOPWATCH_API_KEY", "a-long-enough-secret-key")
    assert Settings().environment == "production"


def test_settings_default_to_a_sqlite_file_in_the_data_directory(monkeypatch, tmp_path):
    monkeypatch.setenv("LOOPWATCH_DATA_DIR", str(tmp_path))
    monkeypatch.delenv("LOOPWATCH_DATABASE_URL", raising=False)
    assert Settings().resolved_database_url == f"sqlite:///{tmp_path / 'loopwatch.db'}"
