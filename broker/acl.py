"""The site's topic access rules, derived once from the site file and enforced by amqtt and Mosquitto alike.

- a node publishes only `zones/<its zone>/state/<itself>`, `nodes/<itself>/status`, `nodes/<itself>/info`
  (its diagnostics), `nodes/<itself>/log` (its last log lines, on command) and `nodes/<itself>/ota/request` (update mode asks for chunks), may read back the first two
  (e.g. to resume its `seq` after a reboot), and reads its own `nodes/<itself>/command` and
  `nodes/<itself>/ota/chunk`, which only the operator writes (a node cannot command or update another);
- a robot reads zones, nodes, operator topics, robots' statuses, its goal and the simulated world, and publishes
  only its status (one topic: it can hold one retained message, never fill the store);
- the operator publishes `operator/...`, node commands (`nodes/+/command`) and update chunks (`nodes/+/ota/chunk`), robot goals, robot statuses (to clear a retained one) and the simulated world (`sim/...`, used by the zone
  simulator), and reads everything of the site; it also publishes and reads Home Assistant's discovery configs
  (`homeassistant/#`, `wsnav broker ha-discovery`); its tools log in as `operator.<tool>` with the same rights
  (schemas.credentials.OPERATOR_TOOLS), so several run at once on Mosquitto;
- the dashboard (Home Assistant) reads everything of the site and the discovery configs, and publishes only
  Home Assistant's own `homeassistant/status`: a dashboard's stolen password moves nothing.
Nothing else outside `wsn/<site>/` is allowed to anyone. The same `AclRules` feed the amqtt plugin below and the
Mosquitto ACL file (wsnav.broker.mosquitto.config), so the two brokers enforce one model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from amqtt.contexts import Action, BaseContext
from amqtt.plugins.base import BaseTopicPlugin
from amqtt.session import Session

from wsnav.broker.credentials import DASHBOARD, OPERATOR
from wsnav.schemas import topics
from wsnav.schemas.credentials import operator_logins
from wsnav.schemas.site_file import SiteFile

HA_DISCOVERY = "homeassistant/#"
"""Home Assistant's default discovery prefix: the operator publishes the site's configs there."""
HA_STATUS = "homeassistant/status"
"""Home Assistant's birth and will (`online` / `offline`), the one topic the dashboard identity writes."""


@dataclass(frozen=True)
class AclRules:
    """username -> topic filters it may publish to / subscribe to."""

    publish: dict[str, list[str]]
    subscribe: dict[str, list[str]]

    def may_publish(self, user: str | None, topic: str) -> bool:
        return user is not None and any(topics.topic_matches(f, topic) for f in self.publish.get(user, ()))

    def may_subscribe(self, user: str | None, topic_filter: str) -> bool:
        return user is not None and any(covers(f, topic_filter) for f in self.subscribe.get(user, ()))


def site_rules(spec: SiteFile) -> AclRules:
    """The rules for every node, robot and the operator of the site (see the module docstring)."""
    site = spec.name
    root = f"{topics.ROOT}/{site}"
    publish: dict[str, list[str]] = {}
    subscribe: dict[str, list[str]] = {}
    for node in spec.nodes:
        own = [topics.zone_state(site, node.zone, node.id), topics.node_status(site, node.id)]
        publish[node.id] = [
            *own,
            topics.node_info(site, node.id),
            topics.node_log(site, node.id),
            topics.node_ota_request(site, node.id),
        ]
        subscribe[node.id] = [*own, topics.node_command(site, node.id), topics.node_ota_chunk(site, node.id)]
    for robot in spec.robots:
        publish[robot.id] = [topics.robot_status(site, robot.id)]
        subscribe[robot.id] = [
            f"{root}/zones/#",
            f"{root}/nodes/#",
            f"{root}/operator/#",
            topics.robot_goal(site, robot.id),
            topics.all_robot_statuses(site),
            f"{root}/sim/#",
        ]
    publish[OPERATOR] = [
        f"{root}/operator/#",
        topics.all_node_commands(site),
        topics.all_node_ota_chunks(site),
        f"{root}/robots/+/goal",
        topics.all_robot_statuses(site),  # to clear a retained status (`wsnav clear-status`)
        f"{root}/sim/#",
        HA_DISCOVERY,
    ]
    subscribe[OPERATOR] = [f"{root}/#", HA_DISCOVERY]
    for login in operator_logins(OPERATOR)[1:]:  # its tools: the same rights under names of their own
        publish[login], subscribe[login] = publish[OPERATOR], subscribe[OPERATOR]
    publish[DASHBOARD] = [HA_STATUS]
    subscribe[DASHBOARD] = [f"{root}/#", HA_DISCOVERY]
    return AclRules(publish=publish, subscribe=subscribe)


def covers(allowed: str, requested: str) -> bool:
    """True when every topic the `requested` filter can match is also matched by `allowed`.

    amqtt's own ACL compares filters level by level as if they were names, so `wsn/+/...` or `#` could slip
    past a rule meant for one site; this checks set inclusion instead.
    """
    a_levels = allowed.split("/")
    r_levels = requested.split("/")
    for i, level in enumerate(a_levels):
        if level == "#":
            return True
        if i >= len(r_levels):
            return False
        wanted = r_levels[i]
        if wanted == "#":
            return False
        if level == "+":
            continue
        if wanted != level:
            return False
    return len(a_levels) == len(r_levels)


class WsnavAclPlugin(BaseTopicPlugin):
    """amqtt topic plugin enforcing `AclRules` on publish and subscribe (refused publishes are dropped)."""

    @dataclass
    class Config(BaseTopicPlugin.Config):
        publish: dict[str, list[str]] = field(default_factory=dict)
        subscribe: dict[str, list[str]] = field(default_factory=dict)

    def __init__(self, context: BaseContext) -> None:
        super().__init__(context)
        config = self.context.config
        assert isinstance(config, WsnavAclPlugin.Config)
        self.rules = AclRules(publish=config.publish, subscribe=config.subscribe)

    async def topic_filtering(
        self, *, session: Session | None = None, topic: str | None = None, action: Action | None = None
    ) -> bool | None:
        if topic is None or session is None:
            return False
        user = session.username
        if action == Action.PUBLISH:
            allowed = self.rules.may_publish(user, topic)
            if not allowed:
                self.context.logger.info(f"refused publish by {user!r} to {topic!r}")
            return allowed
        if action == Action.SUBSCRIBE:
            allowed = self.rules.may_subscribe(user, topic)
            if not allowed:
                self.context.logger.info(f"refused subscription by {user!r} to {topic!r}")
            return allowed
        # RECEIVE: the subscription was checked when it was made; checking again per message costs fan-in time.
        return True
