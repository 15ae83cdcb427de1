"""CMMS fields from the plant file: SAP PM planning plant, work centre and catalogue codes,
Maximo site and organisation, for the plant, a unit or a loop, checked at load."""

from concurrent.futures import ThreadPoolExecutor

import pytest
import yaml
from fastapi.testclient import TestClient

from service.config import ConfigError, Settings, load_plant_config
from service.server import build_service
from tests.service.test_api import ADMIN, T0, plant, simulated_batch

PLANT_CMMS = {"sap_pm": {"planning_plant": "1000", "work_center": "INST-01"},
              "maximo": {"siteid": "BEDFORD", "orgid": "EAGLENA"}}


def with_cmms(unit: dict | None = None, loop: dict | None = None) -> dict:
    """The two-loop test plant as plant-file data, with CMMS settings."""
    data = plant().model_dump(mode="json", exclude_none=True)
    data["cmms"] = PLANT_CMMS
    if unit is not None:
        data["units"][0]["cmms"] = unit
    if loop is not None:
        data["loops"][0]["cmms"] = loop
    return data


def load(tmp_path, data: dict):
    path = tmp_path / "plant.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_plant_config(path)


def test_the_loop_over_its_unit_over_the_plant_field_by_field(tmp_path):
    config = load(tmp_path, with_cmms(
        unit={"sap_pm": {"work_center": "MECH-02"}, "maximo": {"siteid": "TEXAS"}},
        loop={"sap_pm": {"damage_code_group": "PM-VALVE", "damage_code": "STCK",
                         "cause_code_group": "PM-CAUSE", "cause_code": "WEAR"}}))
    fic1, fic2 = config.cmms_of("FIC-1"), config.cmms_of("FIC-2")
    assert fic1.sap_pm.planning_plant == "1000"  # the plant's
    assert fic1.sap_pm.work_center == fic2.sap_pm.work_center == "MECH-02"  # the unit's
    assert fic1.sap_pm.damage_code == "STCK" and fic2.sap_pm.damage_code is None  # FIC-1's
    assert (fic1.maximo.siteid, fic1.maximo.orgid) == ("TEXAS", "EAGLENA")
    assert config.cmms_of("FIC-9") == config.cmms  # a loop no longer configured


@pytest.mark.parametrize(("loop", "message"), [
    ({"sap_pm": {"planning_plant": "10000"}},
     "loops[0].cmms.sap_pm.planning_plant: Value error, SAP planning plant (IWERK) must be 4 "
     "upper-case letters or digits, e.g. '1000', got '10000'"),
    ({"sap_pm": {"work_center": "instrument shop"}},
     "loops[0].cmms.sap_pm.work_center: Value error, SAP work centre (ARBPL) must be 1-8"),
    ({"sap_pm": {"damage_code": "STCK"}},
     "loops[0].cmms.sap_pm: Value error, damage_code_group and damage_code go together"),
    ({"sap_pm": {"cause_code_group": "PM-CAUSE", "cause_code": "WEAR-OUT"}},
     "loops[0].cmms.sap_pm.cause_code: Value error, an SAP catalogue code must be 1-4"),
    ({"maximo": {"siteid": "bedford"}},
     "loops[0].cmms.maximo.siteid: Value error, a Maximo site or organisation id must be"),
    ({"maximo": {"site": "BEDFORD"}}, "loops[0].cmms.maximo.site: Extra inputs are not "
     "permitted"),
])
def test_bad_cmms_settings_are_refused_at_load_with_the_key_path(tmp_path, loop, message):
    with pytest.raises(ConfigError) as error:
        load(tmp_path, with_cmms(loop=loop))
    assert message in str(error.value)
    assert str(tmp_path / "plant.yaml") in str(error.value)


def test_the_cmms_export_and_the_ticket_event_carry_the_settings(tmp_path):
    config = load(tmp_path, with_cmms(loop={"sap_pm": {
        "damage_code_group": "PM-VALVE", "damage_code": "STCK",
        "object_part_code_group": "PM-VPART", "object_part_code": "STEM",
        "cause_code_group": "PM-CAUSE", "cause_code": "WEAR",
        "code_group": "PM-INST", "coding": "CV"}}))
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'lw.db'}", api_key=ADMIN,
                        window_s=3600, buffer_horizon_s=7200, ticket_confirmations=1)
    service = build_service(settings, config, executor=ThreadPoolExecutor(1), clock=lambda: T0)
    client = TestClient(service.app)
    admin = {"X-API-Key": ADMIN}
    client.post("/api/v1/ingest", json=simulated_batch(3600), headers=admin)
    service.scheduler.run_once(T0)
    ticket = client.get("/api/v1/tickets", headers=admin).json()["data"][0]
    cmms = client.get(f"/api/v1/tickets/{ticket['id']}/cmms", headers=admin).json()
    sap = cmms["sap_pm"]
    assert (sap["PLANPLANT"], sap["WORK_CNTR"], sap["CODE_GROUP"], sap["CODING"]) == (
        "1000", "INST-01", "PM-INST", "CV")
    assert sap["ITEM"] == {"D_CODEGRP": "PM-VALVE", "D_CODE": "STCK",
                           "DL_CODEGRP": "PM-VPART", "DL_CODE": "STEM"}
    assert sap["CAUSE"] == {"CAUSE_CODEGRP": "PM-CAUSE", "CAUSE_CODE": "WEAR"}
    assert sap["NOTIF_TYPE"] == "M2" and sap["EQUIPMENT"] == "FV-1"
    assert (cmms["maximo"]["siteid"], cmms["maximo"]["orgid"]) == ("BEDFORD", "EAGLENA")
    service.executor.shutdown()
    service.state.store.close()
