"""The operator's commands to this node (`nodes/<node>/command`, schemas.messages.NodeCommand), on the board.

Loaded for each command `mqtt.MQTTClient.poll` hands over (a live message on the node's own command topic, to
which app.py subscribes after each connect and which the broker's ACL lets only the operator write), and dropped
after (app.py, `Node.iteration`), as main.py drops the config parser: its code is heap the main loop needs the
rest of the time.
"""

import json


def apply(node, body, now_ms: int) -> None:
    """Apply one NodeCommand payload: `restart`, `send_info`, `set_heartbeat` (RAM only; each applied command
    is confirmed by an info at once), `log` (the log ring, schemas.messages.NodeLog), `update` (the update's state written, then a restart into update mode:
    otaboot.py, updater.py), `config` (the same, for a configuration: otaconfig.py; not during a trial).
    Anything else, or a heartbeat outside (0, 3600] s, is counted in the
    info's `bad_commands` and ignored; a command with the last applied id is a QoS 1 redelivery, ignored."""
    try:
        d = json.loads(body)
        if d["id"] == node.command_id:
            return
        cmd = d["command"]
        if d["v"] != 1:
            raise ValueError
        if cmd == "set_heartbeat":
            s = d["heartbeat_s"]
            if type(s) not in (int, float) or not 0 < s <= 3600:
                raise ValueError
            node.logic.heartbeat_ms = int(s * 1000 + 0.5)
        elif cmd == "restart":
            restart(node)
        elif cmd == "update" or cmd == "config":  # a config: fetched and tried the same way (otaconfig.py)
            digest = d["manifest"]
            if type(digest) is not str or len(digest) != 64 or (cmd == "config" and node.trial == 2):
                raise ValueError  # (not during a trial: the old config to go back to is the one tried)
            # Written directly (otaboot's save would load a module on the loop's heap): a write cut short by
            # power is unreadable JSON, which the next boot takes for no update.
            with open("ota.json", "w") as f:
                f.write(
                    '{"stage":"%s","manifest":"%s","boots":0}' % ("fetch" if cmd == "update" else cmd, digest)
                )
            print("update", digest[:8])
            restart(node)  # into update mode (otaboot.boot at the next boot)
        elif cmd == "log":  # its last log lines (app.Node.log) on nodes/<node>/log, QoS 0: an answer, not state
            topic = node.logic.status_topic  # .../nodes/<node>/status
            payload = '{"v":1,"node":"%s","lines":%s}' % (topic.split("/")[3], json.dumps(node.buffer))
            node.client.publish(topic[:-6] + "log", payload)
        elif cmd != "send_info":
            raise ValueError
        node.command_id = d["id"]
        node.info_due_ms = now_ms
    except Exception:  # malformed, unknown, out of range: never a crash
        node.bad_commands += 1
        print("bad command")


def restart(node) -> None:
    """`offline` (retained, acked), DISCONNECT so the broker drops the will, a moment for the radio to send it,
    then a hard reset (on the unix port the process ends and the host starts it again)."""
    import machine

    print("restart")
    client = node.client
    try:
        will = node.logic.will()
        client.publish(will[0], will[1], will[2], will[3])
        client._send(b"\xe0\x00")  # DISCONNECT
        client.close()
    except OSError:
        pass  # reset all the same: the broker publishes the will
    node.feed()
    node.clock.sleep_ms(100)
    machine.reset()
