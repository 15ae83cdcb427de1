"""docker-compose.yml and deploy/: valid for Docker, and consistent with loopwatch itself."""

import os
import shutil
import stat
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.config import Settings, load_plant_config
from service.server import ROLES, ingest_shard
from tests.servers import require

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"
SECRETS = {"POSTGRES_PASSWORD": "compose-test-password",
           "LOOPWATCH_API_KEY": "compose-test-key-0123456789"}


def compose() -> dict[str, Any]:
    document: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return document


def env_file() -> dict[str, str]:
    lines = (ROOT / "deploy" / "loopwatch.env").read_text().splitlines()
    return dict(line.split("=", 1) for line in lines if line and not line.startswith("#"))


def loopwatch_services() -> dict[str, dict[str, Any]]:
    return {name: s for name, s in compose()["services"].items()
            if "LOOPWATCH_ROLE" in s.get("environment", {})}


def resolved(value: str) -> str:
    """A ``${VAR:?..}`` / ``${VAR:-default}`` value with the test's secrets filled in."""
    for name, secret in SECRETS.items():
        value = value.replace(f"${{{name}:?set {name}}}", secret)
        value = value.replace(f"${{{name}:?set {name} (16 characters or more)}}", secret)
    return value.replace("${LOOPWATCH_PLANT_FILE:-}", "")


def compose_command() -> list[str] | None:
    """``docker compose`` (v2) or ``docker-compose`` (v1, Debian's package), if installed."""
    docker = shutil.which("docker")
    if docker is not None and subprocess.run([docker, "compose", "version"],
                                             capture_output=True).returncode == 0:
        return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    return None if legacy is None else [legacy]


def test_docker_compose_accepts_the_file() -> None:
    command = compose_command()
    require(command is not None, "docker compose is not installed here")
    assert command is not None
    config = [*command, "-f", str(COMPOSE), "--project-directory", str(ROOT), "config", "--quiet"]
    done = subprocess.run(config, capture_output=True, text=True,
                          env={**os.environ, **SECRETS})
    assert done.returncode == 0, done.stderr
    missing = subprocess.run(config, capture_output=True, text=True,
                             env={k: v for k, v in os.environ.items() if k not in SECRETS})
    assert missing.returncode != 0 and "set POSTGRES_PASSWORD" in missing.stderr


def test_every_role_runs_and_the_settings_of_each_container_are_valid(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    services = loopwatch_services()
    assert {s["environment"]["LOOPWATCH_ROLE"] for s in services.values()} == set(ROLES) - {
        "all"}
    for name, service in services.items():
        variables = {**env_file(), **{k: resolved(str(v))
                                      for k, v in service["environment"].items()}}
        for variable in variables:
            field = variable.removeprefix("LOOPWATCH_").lower()
            assert field in Settings.model_fields or variable == "LOOPWATCH_PLANT_FILE", (
                f"{name}: {variable} is not a loopwatch setting")
        for variable in [v for v in os.environ if v.startswith("LOOPWATCH_")]:
            monkeypatch.delenv(variable)
        for variable, value in variables.items():
            monkeypatch.setenv(variable, value)
        settings = Settings()  # production: the key and the password must pass its checks
        assert settings.environment == "production"
        assert settings.executor == "dask" and settings.dask_scheduler is not None
        host, port = settings.dask_scheduler.removeprefix("tcp://").split(":")
        assert host in compose()["services"] and port == "8786"


def test_the_ingest_shards_cover_every_index_once() -> None:
    shards = int(env_file()["LOOPWATCH_INGEST_SHARDS"])
    indices = sorted(int(s["environment"]["LOOPWATCH_INGEST_SHARD"])
                     for s in loopwatch_services().values()
                     if s["environment"]["LOOPWATCH_ROLE"] == "ingest")
    assert indices == list(range(shards))
    plant = load_plant_config(ROOT / "deploy" / "plant.yaml")
    endpoints = [c["url"] for c in plant.connectors["opcua"]] + [
        f"{c['host']}:{c['port']}" for c in plant.connectors["modbus"]]
    assert {ingest_shard(e, shards) for e in endpoints} <= set(indices)


def test_the_sample_plant_is_the_plant_service() -> None:
    plant = load_plant_config(ROOT / "deploy" / "plant.yaml")
    assert len(plant.loops) == 9
    assert {c["url"] for c in plant.connectors["opcua"]} == {"opc.tcp://plant:4840"}
    assert {(c["host"], c["port"]) for c in plant.connectors["modbus"]} == {("plant", 5020)}
    command = compose()["services"]["plant"]["entrypoint"]
    assert command[:2] == ["loopwatch", "plant-sim"] and "4840" in command and "5020" in command


def test_the_files_the_compose_file_names_exist() -> None:
    document = compose()
    for name, service in document["services"].items():
        if "build" in service:
            assert (ROOT / service["build"]["context"] / service["build"]["dockerfile"]).is_file()
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith("./"):
                assert (ROOT / source).is_file(), f"{name}: {source}"
    entrypoint = ROOT / "deploy" / "entrypoint.sh"
    assert entrypoint.stat().st_mode & stat.S_IXUSR
    assert "COPY deploy/entrypoint.sh" in (ROOT / "deploy" / "Dockerfile").read_text()


def test_the_entrypoint_passes_the_plant_file_only_when_set(tmp_path: Path) -> None:
    fake = tmp_path / "loopwatch"
    fake.write_text('#!/bin/sh\necho "$@"\n')
    fake.chmod(0o755)
    entrypoint = str(ROOT / "deploy" / "entrypoint.sh")
    env = {"PATH": f"{tmp_path}:/usr/bin:/bin"}
    plain = subprocess.run([entrypoint], env=env, capture_output=True, text=True, check=True)
    assert plain.stdout.split() == ["serve", "--host", "0.0.0.0", "--port", "8000"]
    with_file = subprocess.run([entrypoint], capture_output=True, text=True, check=True,
                               env={**env, "LOOPWATCH_PLANT_FILE": "/etc/loopwatch/plant.yaml"})
    assert with_file.stdout.split()[-2:] == ["--config", "/etc/loopwatch/plant.yaml"]
