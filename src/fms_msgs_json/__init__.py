"""fms_msgs_json: versioned JSON message schemas shared by every fms ROS 2 node.

Nodes exchange ``std_msgs/String`` messages whose ``data`` is one JSON object with ``"schema":
"fms/<kind>/v1"``. This package builds, encodes, decodes and strictly validates those objects without
importing rclpy, so every rule is testable without ROS. Kinds: ``state``, ``command``, ``event``,
``schedule``, ``order``, ``error``, ``replay_request``, ``disruption``, ``replan``; topics and examples are in ``docs/ros.md``.

Typical use::

    text = encode(make_command(run_id, state_seq=12, action="job:0"))  # publisher
    msg = decode(text, expect="command")  # subscriber; raises MessageError (with .code) if bad
"""

from .builders import (
    error_reply, make_command, make_disruption, make_error, make_event, make_order, make_replan,
    make_replay_request, make_schedule, make_state,
)
from .schemas import (
    DISRUPTION_KINDS, ERROR_CODES, ERROR_MAX_BYTES, ERROR_MAX_CHARS, EVENT_KINDS, FEATURE_JOB_COLUMNS, FEATURE_VEHICLE_COLUMNS, KINDS,
    RECEIVED_MAX_CHARS, SCHEMA_COMMAND, SCHEMA_ERROR, SCHEMA_EVENT, SCHEMA_ORDER, SCHEMA_REPLAY_REQUEST,
    SCHEMA_DISRUPTION, SCHEMA_REPLAN, REPLAN_REASONS, REPLAN_STATUSES, REPLAY_WHATS, SCHEMA_SCHEDULE, SCHEMA_STATE, SCHEMA_VERSION, SCHEMAS, TOPIC_COMMAND, TOPIC_DISRUPTIONS,
    TOPIC_ERRORS, TOPIC_EVENTS, TOPIC_ORDERS, TOPIC_REPLANS,
    TOPIC_QOS, TOPIC_REPLAY, TOPIC_SCHEDULE, TOPIC_STATE, TOPICS, MessageError, TopicQos, bounded, decode, encode,
    kind_of, schema_id, validate,
)

from . import builders as _builders, schemas as _schemas

__all__ = [*_schemas.__all__, *_builders.__all__]
