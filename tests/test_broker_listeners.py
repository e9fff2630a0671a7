"""The optional listeners: MQTT over WebSocket and MQTT over TLS, with the same authentication."""

from __future__ import annotations

import datetime
import ipaddress
import os
import ssl
import subprocess
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode

from tests.broker_fixtures import TIMEOUT, wait_listening, wsnav
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.config import BrokerOptions, TlsListener
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF
from wsnav.broker.mosquitto.process import free_port
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site


def self_signed(directory: Path) -> tuple[Path, Path]:
    """A throw-away certificate for 127.0.0.1 (it is its own CA)."""
    pytest.importorskip("cryptography")  # installed with the firmware tools (esptool), not a core dependency
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    certfile, keyfile = directory / "server.crt", directory / "server.key"
    certfile.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    keyfile.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return certfile, keyfile


def connack(client: mqtt.Client, host: str, port: int) -> ReasonCode:
    result: list[ReasonCode] = []
    done = threading.Event()

    def on_connect(_c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        result.append(reason)
        done.set()

    client.on_connect = on_connect
    client.connect(host, port, keepalive=30)
    client.loop_start()
    try:
        assert done.wait(TIMEOUT), "no CONNACK"
        return result[0]
    finally:
        client.disconnect()
        client.loop_stop()


def test_websocket_and_tls_listeners_authenticate(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    certfile, keyfile = self_signed(tmp_path)
    options = BrokerOptions(
        bind=("127.0.0.1", 0),
        ws_bind=("127.0.0.1", 0),
        tls=TlsListener(("127.0.0.1", 0), certfile, keyfile),
    )
    with BrokerThread(site, options=options) as broker:
        assert broker.info is not None
        password = broker.credentials("robot1").password
        ws_host, ws_port = broker.info.extra["ws"]
        tls_host, tls_port = broker.info.extra["tls"]
        for creds in [("robot1", password), ("robot1", "wrong-password-wrong-password")]:
            ws = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="robot1", transport="websockets")
            ws.username_pw_set(*creds)
            assert connack(ws, ws_host, ws_port).is_failure == (creds[1] != password)
            tls = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="robot1")
            tls.tls_set(ca_certs=str(certfile), cert_reqs=ssl.CERT_REQUIRED)
            tls.username_pw_set(*creds)
            assert connack(tls, tls_host, tls_port).is_failure == (creds[1] != password)


def test_the_agents_bus_and_the_operator_commands_work_over_tls_and_refuse_a_wrong_ca(tmp_path: Path) -> None:
    """`--tls-ca`: a goal sent with `wsnav goal` over TLS reaches a robot's bus that logged in over TLS; a CA that
    did not sign the broker's certificate, a file that is no certificate, or the plain port fail in one line."""
    site = tiny_site(tmp_path / "site")
    certfile, keyfile = self_signed(tmp_path)
    (tmp_path / "other").mkdir()
    other_ca, _ = self_signed(tmp_path / "other")
    options = BrokerOptions(bind=("127.0.0.1", 0), tls=TlsListener(("127.0.0.1", 0), certfile, keyfile))
    with BrokerThread(site, options=options) as broker:
        assert broker.info is not None
        tls_host, tls_port = broker.info.extra["tls"]
        robot = connect_with_credentials(tls_host, tls_port, broker.credentials("robot1"), tls_ca=certfile)
        try:
            robot.subscribe(topics.robot_goal("tiny", "robot1"))
            operator_file = broker.info.credentials_dir / "operator.json"

            def goal(port: int, ca: Path) -> subprocess.CompletedProcess[str]:
                return wsnav(
                    "goal", "--site", site, "--broker", f"127.0.0.1:{port}", "--credentials", operator_file,
                    "--tls-ca", ca, "--connect-timeout", "3", "robot1", "B",
                )  # fmt: skip

            sent = goal(tls_port, certfile)
            assert sent.returncode == 0, sent.stderr
            assert robot.wait(TIMEOUT)
            assert [m.topic for m in robot.poll()] == [topics.robot_goal("tiny", "robot1")]
            junk = tmp_path / "junk.pem"
            junk.write_text("not a certificate\n")
            for port, ca, words in (
                (tls_port, other_ca, "over TLS: no answer"),
                (tls_port, junk, "not a readable CA certificate"),
                (broker.port, certfile, "over TLS: no answer"),
            ):
                failed = goal(port, ca)
                assert failed.returncode == 2, failed
                assert words in failed.stderr and "Traceback" not in failed.stderr
                assert len(failed.stderr.strip().splitlines()) == 1, failed.stderr
        finally:
            robot.close()


def test_mosquitto_gets_the_same_tls_listener_from_its_generated_config(tmp_path: Path) -> None:
    """`wsnav broker mosquitto-config --tls-bind ... --certfile ... --keyfile ...`: the real Mosquitto serves
    TLS with the site's passwords and ACL; a goal sent with `wsnav goal --tls-ca` reaches a robot over TLS."""
    mosquitto = require_tool("mosquitto")
    site = tiny_site(tmp_path / "site")
    certfile, keyfile = self_signed(tmp_path)
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    port, tls_port = free_port(), free_port()
    user = ["--user", "root"] if os.geteuid() == 0 else []
    made = wsnav(
        "broker", "mosquitto-config", "--site", site, "--credentials", creds, "--out", tmp_path / "mq",
        "--bind", f"127.0.0.1:{port}", "--data", tmp_path / "mq-data", "--tls-bind", f"127.0.0.1:{tls_port}",
        "--certfile", certfile, "--keyfile", keyfile, *user,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    proc = subprocess.Popen([mosquitto, "-c", str(tmp_path / "mq" / CONF)], stderr=subprocess.PIPE)
    try:
        wait_listening("127.0.0.1", tls_port, proc)
        robot = connect_with_credentials(
            "127.0.0.1", tls_port, load_credentials(creds / "robot1.json"), tls_ca=certfile
        )
        try:
            robot.subscribe(topics.robot_goal("tiny", "robot1"))
            time.sleep(0.5)
            sent = wsnav(
                "goal", "--site", site, "--broker", f"127.0.0.1:{tls_port}", "--credentials",
                creds / "operator.json", "--tls-ca", certfile, "robot1", "B",
            )  # fmt: skip
            assert sent.returncode == 0, sent.stderr
            assert robot.wait(TIMEOUT)
            assert [m.topic for m in robot.poll()] == [topics.robot_goal("tiny", "robot1")]
        finally:
            robot.close()
        wrong = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="robot1")
        wrong.tls_set(ca_certs=str(certfile), cert_reqs=ssl.CERT_REQUIRED)
        wrong.username_pw_set("robot1", "wrong-password-wrong-password")
        assert connack(wrong, "127.0.0.1", tls_port).is_failure
    finally:
        proc.terminate()
        proc.wait(30)
        if proc.stderr:
            proc.stderr.close()
