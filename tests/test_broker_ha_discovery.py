"""Home Assistant MQTT discovery from the site file (`wsnav broker ha-discovery`).

Home Assistant does not install on Python 3.11 here, so the payloads are checked against its documented MQTT
discovery schema (the discovery topic format, the binary_sensor keys and their documented abbreviations, the
required ones), and their value templates are rendered with Jinja2, the engine Home Assistant's templates use,
against the exact payloads our nodes send. The command itself runs against the real broker, whose ACL lets only
the operator write `homeassistant/#`.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import jinja2
import pytest

from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.ha_discovery import discovery_messages
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import NodeInfo, NodeStatus, ZoneState, ZoneStateValue
from wsnav.schemas.site import load_site

DISCOVERY_TOPIC = re.compile(r"^homeassistant/binary_sensor/(?:[a-zA-Z0-9_-]+/)?[a-zA-Z0-9_-]+/config$")
"""`<discovery_prefix>/<component>/[<node_id>/]<object_id>/config`, ids of [a-zA-Z0-9_-] (HA's MQTT docs)."""

BINARY_SENSOR_KEYS = {
    # documented key: its documented abbreviation (HA's MQTT discovery "abbreviations" table)
    "availability": "avty",
    "availability_mode": "avty_mode",
    "availability_template": "avty_tpl",
    "availability_topic": "avty_t",
    "device": "dev",
    "device_class": "dev_cla",
    "enabled_by_default": "en",
    "encoding": "e",
    "entity_category": "ent_cat",
    "expire_after": "exp_aft",
    "force_update": "frc_upd",
    "icon": "ic",
    "json_attributes_template": "json_attr_tpl",
    "json_attributes_topic": "json_attr_t",
    "name": "name",
    "object_id": "obj_id",
    "off_delay": "off_dly",
    "origin": "o",
    "payload_available": "pl_avail",
    "payload_not_available": "pl_not_avail",
    "payload_off": "pl_off",
    "payload_on": "pl_on",
    "qos": "qos",
    "state_topic": "stat_t",
    "unique_id": "uniq_id",
    "value_template": "val_tpl",
}
REQUIRED = {"state_topic"}
"""binary_sensor's one required key; `unique_id` and `device` are what puts the entity in HA's registry."""
AVAILABILITY_KEYS = {"topic": "t", "payload_available": "pl_avail", "payload_not_available": "pl_not_avail"}
AVAILABILITY_KEYS["value_template"] = "val_tpl"
DEVICE_KEYS = {"identifiers": "ids", "name": "name", "model": "mdl", "manufacturer": "mf", "sw_version": "sw"}
ORIGIN_KEYS = {"name": "name", "sw_version": "sw", "support_url": "url"}
BINARY_SENSOR_DEVICE_CLASSES = {"connectivity", "occupancy", "motion", "presence", "problem", "safety"}
ENTITY_CATEGORIES = {"config", "diagnostic"}


def render(template: str, payload: bytes) -> str:
    """What Home Assistant does with a value template: Jinja2 with `value` and the parsed `value_json`."""
    import json

    return jinja2.Template(template).render(value=payload.decode(), value_json=json.loads(payload)).strip()


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_site(tmp_path_factory.mktemp("site"))


def configs(site_dir: Path) -> dict[str, dict[str, Any]]:
    import json

    return {t: json.loads(p) for t, p in discovery_messages(load_site(site_dir).spec)}


def test_every_config_follows_home_assistants_documented_discovery_schema(site_dir: Path) -> None:
    spec = load_site(site_dir).spec
    found = configs(site_dir)
    assert len(found) == 2 * len(spec.nodes)  # a zone sensor per watching node, a link sensor per node
    unique_ids = set()
    for topic, config in found.items():
        assert DISCOVERY_TOPIC.match(topic), topic
        assert set(config) <= set(BINARY_SENSOR_KEYS), set(config) - set(BINARY_SENSOR_KEYS)
        assert set(config) >= REQUIRED and config["unique_id"] not in unique_ids
        unique_ids.add(config["unique_id"])
        assert config["device_class"] in BINARY_SENSOR_DEVICE_CLASSES
        assert config.get("entity_category", "diagnostic") in ENTITY_CATEGORIES
        assert set(config["device"]) <= set(DEVICE_KEYS) and config["device"]["identifiers"]
        assert set(config["origin"]) <= set(ORIGIN_KEYS) and config["origin"]["name"]
        for item in config.get("availability", []):
            assert set(item) <= set(AVAILABILITY_KEYS) and "topic" in item  # `topic` is required there
            assert topics.parse(item["topic"]) is not None
        assert topics.parse(config["state_topic"]) is not None  # a topic of our contract, nothing invented
    # The documented abbreviations are unique, so a config written with them would mean the same.
    assert len(set(BINARY_SENSOR_KEYS.values())) == len(BINARY_SENSOR_KEYS)


def test_the_templates_turn_our_payloads_into_on_and_off(site_dir: Path) -> None:
    found = configs(site_dir)
    zone = found["homeassistant/binary_sensor/wsnav_tiny/z1_n1/config"]
    link = found["homeassistant/binary_sensor/wsnav_tiny/n1_link/config"]
    assert zone["state_topic"] == topics.zone_state("tiny", "z1", "n1")
    states: list[tuple[ZoneStateValue, str]] = [("clear", "OFF"), ("caution", "ON"), ("blocked", "ON")]
    for state, shown in states:
        payload = ZoneState(zone="z1", node="n1", state=state, seq=3).to_payload()
        assert render(zone["value_template"], payload) == zone[f"payload_{shown.lower()}"]
    for payload, shown in (
        (NodeStatus(node="n1", status="online").to_payload(), "ON"),
        (NodeStatus(node="n1", status="offline").to_payload(), "OFF"),
    ):
        assert render(link["value_template"], payload) == link[f"payload_{shown.lower()}"]
        # The zone sensor is unavailable, not stale, while its node is offline.
        avail = zone["availability"][0]
        assert avail["topic"] == topics.node_status("tiny", "n1")
        assert (
            render(avail["value_template"], payload)
            == avail[f"payload_{'' if shown == 'ON' else 'not_'}available"]
        )
    assert link["json_attributes_topic"] == topics.node_info("tiny", "n1")  # diagnostics as attributes
    info = NodeInfo(node="n1", fw="0.2.0", reset="power_on", uptime_s=5, reconnects=0).to_payload()
    assert render("{{ value_json.reset }}", info) == "power_on"


def wsnav(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *map(str, args)], capture_output=True, text=True, timeout=120
    )


def test_the_operator_publishes_discovery_retained_and_a_node_cannot(site_dir: Path, tmp_path: Path) -> None:
    creds = tmp_path / "creds"
    write_credentials(load_site(site_dir).spec, creds)
    with BrokerThread(site_dir, creds) as broker:
        address = f"{broker.host}:{broker.port}"
        refused = wsnav(
            "broker",
            "ha-discovery",
            "--site",
            site_dir,
            "--broker",
            address,
            "--credentials",
            creds / "n1.json",
        )
        assert refused.returncode != 0 and "Traceback" not in refused.stderr
        # One error line (after the bus's own note that the broker refused its subscription).
        last = refused.stderr.strip().splitlines()[-1]
        assert last.startswith("wsnav: error:") and "may 'n1' publish and read homeassistant/#" in last
        done = wsnav(
            "broker",
            "ha-discovery",
            "--site",
            site_dir,
            "--broker",
            address,
            "--credentials",
            creds / "operator.json",
        )
        assert done.returncode == 0, done.stderr
        # What a Home Assistant connecting later finds: every config, retained.
        bus = connect_with_credentials(
            broker.host, broker.port, load_credentials(creds / "operator.json"), client_id="ha-check"
        )
        try:
            bus.subscribe("homeassistant/#")
            want = dict(discovery_messages(load_site(site_dir).spec))
            got: dict[str, bytes] = {}
            deadline = time.monotonic() + 30
            while set(got) != set(want) and time.monotonic() < deadline:
                bus.wait(0.5)
                got.update((m.topic, m.payload) for m in bus.poll())
        finally:
            bus.close()
        assert got == want
