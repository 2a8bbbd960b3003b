"""Step outcomes published in a namespace that is not among trainer_node's actors: found by a scan of the graph,
reported once each, counted (the node's `unknown_actor_messages`) and never learnt from."""

from __future__ import annotations

from uav_common import contract
from uav_interfaces.msg import StepOutcome

SCAN_S = 2.0  # how often the graph is searched


class UnknownActors:
    def __init__(self, node, actors, counts: dict):
        self.node, self.actors, self.counts = node, actors, counts
        self.counts["unknown_actor_messages"] = 0
        self.subscriptions: dict[str, object] = {}  # step_outcome topics outside the actors: what counts them
        node.create_timer(SCAN_S, self.scan)

    def scan(self) -> None:
        known = {a.outcome_topic for a in self.actors}
        suffix = "/" + contract.OUTCOME_TOPIC
        for topic, _types in self.node.get_topic_names_and_types():
            if not topic.endswith(suffix) or topic in known or topic in self.subscriptions:
                continue
            ns = topic[: -len(suffix)] or "/"
            self.node.get_logger().warning(
                f"ignoring {topic}: namespace {ns} is not among the actors {[a.ns or '(this namespace)' for a in self.actors]} "
                "(its messages are counted on /diagnostics as unknown_actor_messages)"
            )
            self.subscriptions[topic] = self.node.create_subscription(StepOutcome, topic, self._count, contract.DEEP_QOS)

    def _count(self, _msg: StepOutcome) -> None:
        self.counts["unknown_actor_messages"] += 1
