"""`wsnav broker credentials` and `mosquitto-config`: owner-only files, kept secrets, node configs from the site,
and Mosquitto's password format produced without Mosquitto's tools."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.broker_fixtures import store_guard_plugin, wait_listening
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.credentials import (
    PASSWORD_FILE,
    read_password_file,
    verify_password,
    write_credentials,
)
from wsnav.broker.mosquitto.config import (
    ACL,
    CONF,
    PASSWORDS,
    MosquittoOptions,
    mosquitto_hash,
    write_mosquitto_config,
)
from wsnav.broker.mosquitto.plugin import JOURNAL, PLUGIN
from wsnav.broker.mosquitto.process import free_port
from wsnav.broker.mosquitto.store import STORE
from wsnav.schemas.credentials import (
    OPERATOR_TOOLS,
    UPDATE_KEY_FILE,
    Credentials,
    NodeConfig,
    load_credentials,
    node_update_key,
    operator_logins,
)
from wsnav.schemas.site import load_site


def wsnav(*args: str | Path, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *map(str, args)],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=120,
    )


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_files_for_every_id_owner_only(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    out = tmp_path / "creds"
    result = wsnav("broker", "credentials", "--site", site, "--out", out, "--broker", "10.0.0.2:1883")
    assert result.returncode == 0, result.stderr
    assert mode(out) == 0o700
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        [
            PASSWORD_FILE,
            UPDATE_KEY_FILE,
            "n1.json",
            "n2.json",
            "robot1.json",
            "operator.json",
            "dashboard.json",
        ]
    )
    assert all(mode(p) == 0o600 for p in out.iterdir())
    node = NodeConfig.model_validate_json((out / "n2.json").read_text())
    assert (node.node, node.zone, node.sensor.type, node.heartbeat_s) == ("n2", "z2", "hcsr04", 5.0)
    assert (node.on_delay_ms, node.off_delay_ms, node.broker.host, node.broker.port) == (
        500,
        3000,
        "10.0.0.2",
        1883,
    )
    robot = Credentials.model_validate_json((out / "robot1.json").read_text())
    assert robot.role == "robot"
    assert Credentials.model_validate_json((out / "operator.json").read_text()).role == "operator"
    hashes = read_password_file(out / PASSWORD_FILE)
    assert set(hashes) == {"n1", "n2", "robot1", "dashboard", *operator_logins("operator")}
    operator = Credentials.model_validate_json((out / "operator.json").read_text())
    assert all(verify_password(hashes[f"operator.{tool}"], operator.password) for tool in OPERATOR_TOOLS)
    assert Credentials.model_validate_json((out / "dashboard.json").read_text()).role == "dashboard"
    assert verify_password(hashes["n2"], node.password)
    assert not verify_password(hashes["n1"], node.password)
    site_key = (out / UPDATE_KEY_FILE).read_text().strip()
    n1 = NodeConfig.model_validate_json((out / "n1.json").read_text())
    assert node.update_key == node_update_key(site_key, "n2") and n1.update_key == node_update_key(
        site_key, "n1"
    )
    assert len({site_key, node.update_key, n1.update_key, node.password, n1.password}) == 5


def test_rerun_keeps_secrets_adds_new_ids_reports_removed(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    out = tmp_path / "creds"
    assert wsnav("broker", "credentials", "--site", site, "--out", out).returncode == 0
    before = {p.name: json.loads(p.read_text())["password"] for p in out.glob("*.json")}
    before_key = (out / UPDATE_KEY_FILE).read_text()
    tiny_site(
        site,
        nodes=[
            {"id": "n1", "zone": "z1", "sensor": {"type": "pir", "pin": 5}, "heartbeat_s": 2},
            {"id": "n3", "zone": "z2", "sensor": {"type": "ir_beam", "pin": 4}},
        ],
    )
    result = wsnav("broker", "credentials", "--site", site, "--out", out)
    assert result.returncode == 0, result.stderr
    after = {p.name: json.loads(p.read_text())["password"] for p in out.glob("*.json")}
    after_key = (out / UPDATE_KEY_FILE).read_text()
    assert after["n1.json"] == before["n1.json"] and after["robot1.json"] == before["robot1.json"]
    assert "n3.json" in after and after["n3.json"] not in before.values()
    assert "n2.json" in after  # left in place ...
    assert "n2" not in read_password_file(out / PASSWORD_FILE)  # ... but can no longer log in
    assert "n2.json: n2 is no longer in the site" in result.stdout
    assert NodeConfig.model_validate_json((out / "n1.json").read_text()).heartbeat_s == 2.0
    assert after_key == before_key  # the update key is kept: deployed nodes keep taking updates


def test_a_damaged_update_key_is_one_line_and_not_replaced(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    out = tmp_path / "creds"
    assert wsnav("broker", "credentials", "--site", site, "--out", out).returncode == 0
    (out / UPDATE_KEY_FILE).write_text("not a key\n")
    result = wsnav("broker", "credentials", "--site", site, "--out", out)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"wsnav: error: {out / UPDATE_KEY_FILE}: not an update key (64 hex digits); restore it from a backup"
    ]
    assert (out / UPDATE_KEY_FILE).read_text() == "not a key\n"


def test_wifi_set_for_every_node_and_the_key_read_from_stdin(tmp_path: Path) -> None:
    """The installer's Wi-Fi goes into every node's config without editing JSON; `-` keeps the key off the
    command line, and an empty stdin is refused without touching the files written before."""
    site = tiny_site(tmp_path / "site")
    out = tmp_path / "creds"
    result = wsnav(
        *("broker", "credentials", "--site", site, "--out", out),
        *("--wifi-ssid", "site-iot", "--wifi-password", "-"),
        stdin="s3cret key\n",
    )
    assert result.returncode == 0, result.stderr
    for name in ("n1.json", "n2.json"):
        wifi = NodeConfig.model_validate_json((out / name).read_text()).wifi
        assert (wifi.ssid, wifi.password) == ("site-iot", "s3cret key")
    before = (out / "n1.json").read_text()
    empty = wsnav("broker", "credentials", "--site", site, "--out", out, "--wifi-password", "-", stdin="")
    assert empty.returncode != 0
    assert len(empty.stderr.splitlines()) == 1 and "stdin gave no password" in empty.stderr
    assert (out / "n1.json").read_text() == before


def test_damaged_existing_file_is_not_replaced(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    out = tmp_path / "creds"
    assert wsnav("broker", "credentials", "--site", site, "--out", out).returncode == 0
    (out / "n1.json").write_text("{not json")
    result = wsnav("broker", "credentials", "--site", site, "--out", out)
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1 and "n1.json: not valid JSON" in result.stderr
    assert (out / "n1.json").read_text() == "{not json"


def test_missing_site_is_one_line(tmp_path: Path) -> None:
    result = wsnav("broker", "credentials", "--site", tmp_path / "nowhere", "--out", tmp_path / "c")
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1 and "no such site file" in result.stderr


def test_mosquitto_hash_matches_mosquitto_passwd_format() -> None:
    # Computed once with `mosquitto_passwd -b` (2.0.11) for password "secretsecret".
    reference = "$7$101$JEUYz8QdMzOm6BD0$CpC6Mf6KerTRs6XBHL12OWTkK4w+MlSX1qfWymz/U1ZGeYKyC5b39RJGqCI2ogVnimAFeSikM86RPILfZf8WFQ=="
    import base64

    salt = base64.b64decode(reference.split("$")[3])
    assert mosquitto_hash("secretsecret", salt) == reference


def test_mosquitto_config_files(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    creds, out = tmp_path / "creds", tmp_path / "mosq"
    assert wsnav("broker", "credentials", "--site", site, "--out", creds).returncode == 0
    result = wsnav("broker", "mosquitto-config", "--site", site, "--credentials", creds, "--out", out)
    assert result.returncode == 0, result.stderr
    conf = (out / CONF).read_text()
    for line in (
        "allow_anonymous false",
        "set_tcp_nodelay true",
        "persistence true",
        f"acl_file {out / ACL}",
    ):
        assert line in conf.splitlines()
    acl = (out / ACL).read_text()
    assert "user n1\ntopic write wsn/tiny/zones/z1/state/n1\ntopic write wsn/tiny/nodes/n1/status\n" in acl
    users = [line.split(":")[0] for line in (out / PASSWORDS).read_text().splitlines()]
    assert sorted(users) == sorted(["dashboard", "n1", "n2", "robot1", *operator_logins("operator")])
    assert all(mode(p) == 0o600 for p in out.iterdir())


def test_mosquitto_config_store_guard_builds_the_plugin_from_the_repo_and_loads_it(tmp_path: Path) -> None:
    """`--store-guard` compiles wsnav's plugin here (nothing prebuilt ships) and the config loads it, journaling
    this site's operator blocks beside the store (tests/test_broker_process.py and test_broker_storage.py run it)."""
    site = tiny_site(tmp_path / "site")
    creds, out, data = tmp_path / "creds", tmp_path / "mosq", tmp_path / "data"
    assert wsnav("broker", "credentials", "--site", site, "--out", creds).returncode == 0
    store_guard_plugin(
        tmp_path / "probe"
    )  # skips (fails under WSNAV_REQUIRE_TOOLS=1) without gcc/mosquitto-dev
    args = (
        "broker",
        "mosquitto-config",
        "--site",
        site,
        "--credentials",
        creds,
        "--out",
        out,
        "--data",
        data,
    )
    result = wsnav(*args, "--store-guard")
    assert result.returncode == 0, result.stderr
    conf = (out / CONF).read_text().splitlines()
    for line in (
        f"plugin {out.resolve() / PLUGIN}",
        f"plugin_opt_journal {data.resolve() / JOURNAL}",
        "plugin_opt_topic_prefix wsn/tiny/operator/blocks/",
        f"plugin_opt_store {data.resolve() / STORE}",
    ):
        assert line in conf
    assert (out / PLUGIN).is_file() and f"built {out.resolve() / PLUGIN}" in result.stdout
    plain = wsnav(*args)
    assert plain.returncode == 0 and not [
        line for line in (out / CONF).read_text().splitlines() if "plugin" in line
    ]


def test_mosquitto_config_creates_the_persistence_folder_for_the_brokers_user(tmp_path: Path) -> None:
    """Without its --data folder Mosquitto logged "No such file or directory" every minute and lost an operator
    block at a restart; as root, the folder and the files go to --user (Mosquitto reads them as that user)."""
    import os
    import pwd

    site = tiny_site(tmp_path / "site")
    creds, out, data = tmp_path / "creds", tmp_path / "mosq", tmp_path / "var" / "lib" / "mq"
    assert wsnav("broker", "credentials", "--site", site, "--out", creds).returncode == 0
    args = [
        "broker",
        "mosquitto-config",
        "--site",
        site,
        "--credentials",
        creds,
        "--out",
        out,
        "--data",
        data,
    ]
    as_root = os.geteuid() == 0
    result = wsnav(*args, *(["--user", "nobody"] if as_root else []))
    assert result.returncode == 0, result.stderr
    assert data.is_dir() and mode(data) == 0o700
    assert f"persistence_location {data}/" in (out / CONF).read_text().splitlines()
    if as_root:
        nobody = pwd.getpwnam("nobody").pw_uid
        assert {p.stat().st_uid for p in [data, out, *out.iterdir()]} == {nobody}
        wrong = wsnav(*args, "--user", "no-such-user-here")
        assert wrong.returncode == 2 and wrong.stderr.count("\n") == 1
        assert "--user no-such-user-here: no such system user" in wrong.stderr


@pytest.mark.parametrize("broken", ["missing", "bad"])
def test_mosquitto_config_bad_credentials_is_one_line(tmp_path: Path, broken: str) -> None:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    assert wsnav("broker", "credentials", "--site", site, "--out", creds).returncode == 0
    if broken == "missing":
        (creds / "robot1.json").unlink()
    else:
        (creds / "robot1.json").write_text('{"username": "robot1"}')
    result = wsnav(
        "broker", "mosquitto-config", "--site", site, "--credentials", creds, "--out", tmp_path / "m"
    )
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1 and "robot1.json" in result.stderr


def test_mosquitto_keeps_messages_for_a_subscriber_that_stalls(tmp_path: Path) -> None:
    """A robot whose loop stalls while 3000 zone states arrive gets every one of them once it reads again
    (Mosquitto's own default queue, 1000 messages, dropped the rest)."""
    mosquitto = require_tool("mosquitto")
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    port = free_port()
    (tmp_path / "data").mkdir()
    options = MosquittoOptions(
        bind=("127.0.0.1", port), data_dir=tmp_path / "data", user="root" if os.geteuid() == 0 else None
    )
    write_mosquitto_config(load_site(site).spec, creds, tmp_path / "conf", options)
    proc = subprocess.Popen([mosquitto, "-c", str(tmp_path / "conf" / CONF)], stderr=subprocess.DEVNULL)
    try:
        wait_listening("127.0.0.1", port, proc)
        got: list[int] = []
        robot = paho_client(creds, "robot1", port)
        robot.on_message = lambda _c, _u, m: got.append(json.loads(m.payload)["seq"])
        robot.subscribe("wsn/tiny/zones/+/state/+", qos=1)
        robot.loop(1.0)
        robot.loop(0.2)
        node = paho_client(creds, "n1", port)
        node.loop_start()
        topic = "wsn/tiny/zones/z1/state/n1"
        for seq in range(3000):  # the robot is not reading: Mosquitto queues what it cannot send
            payload = json.dumps({"zone": "z1", "node": "n1", "state": "clear", "seq": seq})
            node.publish(topic, payload, qos=1).wait_for_publish(5)
        node.loop_stop()
        deadline = time.monotonic() + 30
        while len(got) < 3000 and time.monotonic() < deadline:
            robot.loop(0.1)
        assert sorted(set(got)) == list(range(3000)), f"{3000 - len(set(got))} of 3000 lost"
    finally:
        proc.terminate()
        proc.wait(30)


def paho_client(creds: Path, ident: str, port: int) -> mqtt.Client:
    c = load_credentials(creds / f"{ident}.json")
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=ident)
    client.username_pw_set(c.username, c.password)
    client.connect("127.0.0.1", port)
    return client
