"""``fms send``: send an order or a disruption to a running shop over ROS 2 and say how the shop answered.

A shop node takes new jobs on ``fms/orders`` and machine breakdowns or vehicle outages on ``fms/disruptions``
(docs/ros.md). Factory software publishes them itself; an operator needs a command, and the ROS 2 wheels from PyPI
bring no ``ros2`` command line (``ros2 topic pub``). ``fms send order|breakdown|outage`` builds the message
(``fms_msgs_json.make_order`` / ``make_disruption``: checked before anything is sent), waits until a shop listens
on the ROS domain that ``--domain-id`` or ``ROS_DOMAIN_ID`` names (``fms up`` prints its domain), publishes it and
waits for the shop's answer: the ``order_accepted`` or ``disruption_accepted`` event naming its id (exit code 0;
an order's line lists the job numbers the shop gave the new jobs), or the error the shop published about it (exit
code 1). No shop within ``--timeout`` seconds, or no answer: exit code 1. Bad input, or no domain given: exit
code 2, before anything is sent; so is a message without ``--run-id`` where several nodes listen on its topic (shops
of several runs on one domain: each would take it), and one that a second run is found taking too is exit code 1. Like ``fms up``, it sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless set.

The message building and the reading of the shop's answer (:func:`build`, :func:`answer`) need no ROS; rclpy is
imported only to send (:func:`exchange`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import uuid
from typing import Any, Sequence

from fms_msgs_json import (
    SCHEMA_ORDER, TOPIC_ERRORS, TOPIC_EVENTS, TOPICS, MessageError, decode, encode, make_disruption, make_order,
)
from fms_sim.files import loads, read_text

__all__ = ["add_send_parser", "cmd_send", "build", "answer", "exchange", "main", "SendError"]

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
SOURCE = "fms_send"


class SendError(ValueError):
    """Bad input for ``fms send`` (exit code 2)."""


def add_send_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``send`` subcommand to an ``argparse`` subparsers object; it sets ``fn=cmd_send``."""
    p = subparsers.add_parser(
        "send", help="send an order or a disruption to a running shop (ROS 2) and print the shop's answer",
        description="Send new jobs, a machine breakdown or a vehicle outage to a running shop node over ROS 2 "
                    "and wait for its answer (docs/ros.md).")
    _add_arguments(p)
    p.set_defaults(fn=cmd_send)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="what", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--id", help="the message's id (default: <kind>-<UTC time>-<random>); a shop accepts an id "
                                     "once")
    common.add_argument("--run-id", help="only for this run (default: the shop's current run)")
    common.add_argument("--domain-id", type=int, help="the shop's ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID; fms up "
                                                      "prints the one it uses)")
    common.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for a shop and its answer (default 10)")
    o = sub.add_parser("order", parents=[common], help="new jobs",
                       description="Send new jobs. --jobs is JSON (or @FILE): a list of jobs, each a list of "
                                   "operations {\"machine\": M, \"tool\": T or null, \"duration\": D} or [M, T, D] "
                                   "or [M, D]; a file may also hold a whole fms/order/v1 message (its "
                                   "order_id and run_id are used unless --id or --run-id are given).")
    o.add_argument("--jobs", required=True, metavar="JSON|@FILE")
    b = sub.add_parser("breakdown", parents=[common], help="a machine breakdown")
    b.add_argument("--machine", type=int, required=True)
    b.add_argument("--duration", type=int, required=True)
    b.add_argument("--start", type=int, help="the shop time it begins (default: now)")
    u = sub.add_parser("outage", parents=[common], help="a vehicle out of service")
    u.add_argument("--vehicle", required=True, metavar="agv:V|tt:V", help="an AGV or tool transporter, from 0")
    u.add_argument("--duration", type=int, required=True)
    u.add_argument("--start", type=int, help="the shop time it begins (default: now)")


def _order(spec: str) -> tuple[Any, Any, Any]:
    """What ``--jobs`` holds: JSON, or ``@FILE`` holding JSON: a list of jobs, or a whole ``fms/order/v1`` message
    (then its ``order_id`` and ``run_id`` too, None where it has none): ``(jobs, order_id, run_id)``."""
    if spec.startswith("@"):
        if not spec[1:].strip():  # "cannot read : Is a directory"
            raise SendError("--jobs @ names no file; give @FILE")
        try:
            text = read_text(spec[1:])
        except OSError as exc:
            raise SendError(f"cannot read {spec[1:]}: {exc.strerror or exc}") from None
        except UnicodeDecodeError:
            raise SendError(f"{spec[1:]} is not a text (UTF-8 JSON) file") from None
    else:
        text = spec
    try:  # (a key twice in one object is refused too: docs/ros.md calls it malformed JSON)
        jobs = loads(text)
    except json.JSONDecodeError as exc:
        raise SendError(f"--jobs is not JSON: {exc}") from None
    if isinstance(jobs, dict):  # a whole order message: its id and run too (re-sending the file is the same order)
        if jobs.get("schema", SCHEMA_ORDER) != SCHEMA_ORDER:  # an fms/order/v2 or a disruption was sent as v1
            raise SendError(f"--jobs holds a {jobs['schema']!r} message, not an order ({SCHEMA_ORDER})")
        if "jobs" not in jobs:  # it said "field 'jobs' must be a non-empty array, got an object"
            raise SendError(f"--jobs holds an object without 'jobs': give a list of jobs or a whole {SCHEMA_ORDER} "
                            "message")
        return jobs["jobs"], jobs.get("order_id"), jobs.get("run_id")
    return jobs, None, None


def build(a: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    """The message the arguments describe, checked: ``("order" | "disruption", message)``; raises
    :class:`SendError`."""
    if a.id is not None and not a.id.strip():  # an empty id was replaced by a generated one without a word
        raise SendError("--id must be a non-empty name (leave it out for a generated one)")
    mid = a.id or f"{a.what}-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}-{uuid.uuid4().hex[:6]}"
    try:
        if a.what == "order":  # --id and --run-id win over a message file's own
            jobs, order_id, run_id = _order(a.jobs)
            # (a message's empty order_id is refused by make_order: it was replaced by a generated one without a word)
            return "order", make_order(a.id or (mid if order_id is None else order_id), jobs,
                                       run_id=a.run_id or run_id)
        if a.what == "breakdown":
            return "disruption", make_disruption(mid, "breakdown", a.duration, machine=a.machine, start=a.start,
                                                 run_id=a.run_id)
        kind, _, number = a.vehicle.partition(":")
        if kind not in ("agv", "tt") or not (number.isascii() and number.isdigit()):  # ('²' and '٣' are digits)
            raise SendError(f"--vehicle must be agv:V or tt:V with V a vehicle number from 0, got {a.vehicle!r}")
        return "disruption", make_disruption(mid, "outage", a.duration, vehicle_kind=kind, vehicle=int(number),
                                             start=a.start, run_id=a.run_id)
    except MessageError as exc:
        raise SendError(str(exc)) from None


def answer(kind: str, msg: dict[str, Any], text: str, topic: str, incoming: dict[str, Any]) -> tuple[bool, str] | None:
    """The shop's answer to ``msg`` (sent as ``text``) if ``incoming`` (decoded, from ``topic``) is it:
    ``(accepted, a line to print)``; None for any other message. An acceptance is the event naming the id; a
    refusal is an error whose ``received`` text is (the start of) ``text``."""
    key = f"{kind}_id"
    if topic == TOPIC_EVENTS and incoming.get("kind") == f"{kind}_accepted" and incoming["data"].get(key) == msg[key]:
        data = incoming["data"]
        if kind == "order":
            jobs = ", ".join(str(j) for j in data["jobs"])
            return True, f"order {msg[key]} accepted by run {incoming['run_id']} at time {incoming['time']}: jobs {jobs}"
        what = (f"machine {data['machine']}" if data["disruption"] == "breakdown"
                else f"{data['vehicle_kind']} {data['vehicle']}")
        return True, (f"{data['disruption']} {msg[key]} ({what}, from time {data['start']} for {data['duration']}) "
                      f"accepted by run {incoming['run_id']}")
    received = incoming.get("received")
    if topic == TOPIC_ERRORS and received and text.startswith(received):
        return False, f"refused by {incoming['source']}: [{incoming['code']}] {incoming['message']}"
    return None


def _heard_answers(node: Any, heard: list[tuple[str, str]], kind: str, msg: dict[str, Any],
                   text: str) -> list[tuple[dict[str, Any], tuple[bool, str]]]:
    """Spin ``node`` once and return the messages heard since (``heard``, then emptied) that answer ``msg``: each
    decoded, with its :func:`answer`."""
    import rclpy

    rclpy.spin_once(node, timeout_sec=0.05)
    out = []
    for t, data in heard:
        try:
            incoming = decode(data, expect="event" if t == TOPIC_EVENTS else "error")
        except MessageError:
            continue
        got = answer(kind, msg, text, t, incoming)
        if got is not None:
            out.append((incoming, got))
    heard.clear()
    return out


def _only_taker(node: Any, heard: list[tuple[str, str]], kind: str, msg: dict[str, Any], text: str, run: str,
                line: str) -> tuple[int, str]:
    """After a message for "the current run" was accepted by ``run``: listen 0.5 s more for another run taking it too
    (a shop the check before sending had not yet seen); ``(exit code, line)``."""
    takers = [run]
    heard.clear()
    until = time.monotonic() + 0.5
    while time.monotonic() < until:
        for incoming, (accepted, _) in _heard_answers(node, heard, kind, msg, text):
            if accepted and incoming["run_id"] not in takers:
                takers.append(incoming["run_id"])
    if len(takers) > 1:
        return EXIT_FAILED, (f"{kind} {msg[f'{kind}_id']} was taken by {len(takers)} runs ({', '.join(takers)}): "
                             "shops of several runs on this domain; name one with --run-id")
    return EXIT_OK, line


def exchange(kind: str, msg: dict[str, Any], timeout: float) -> tuple[int, str]:
    """Send ``msg`` on the topic of ``kind`` once a shop listens there and wait for its :func:`answer`: ``(exit
    code, line)``. Needs rclpy."""
    import rclpy
    from std_msgs.msg import String

    from fms_sim.shop_node import qos_profile

    from rclpy.signals import SignalHandlerOptions

    from .up import _TermAsInterrupt

    text = encode(msg)
    topic = TOPICS[kind]
    # rclpy's own handlers turned SIGTERM (and SIGINT to a background job) into a shutdown that spin_once raised as
    # a traceback; without them SIGTERM and SIGINT are a KeyboardInterrupt: "interrupted", exit 130
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    stop = _TermAsInterrupt()
    node = rclpy.create_node(f"{SOURCE}_{uuid.uuid4().hex[:8]}")
    heard: list[tuple[str, str]] = []
    try:
        subs = [node.create_subscription(String, TOPICS[k], lambda m, t=TOPICS[k]: heard.append((t, m.data)),
                                         qos_profile(k)) for k in ("event", "error")]
        pub = node.create_publisher(String, topic, qos_profile(kind))
        deadline = time.monotonic() + timeout
        # the shop listens on the topic and publishes the events that answer: both matched before sending
        while pub.get_subscription_count() == 0 or any(s.get_publisher_count() == 0 for s in subs):
            if time.monotonic() > deadline:
                return EXIT_FAILED, (f"no shop listens on {topic} within {timeout:g} s (ROS_DOMAIN_ID="
                                     f"{os.environ.get('ROS_DOMAIN_ID')}; fms up prints the domain it uses)")
            rclpy.spin_once(node, timeout_sec=0.05)
        if msg.get("run_id") is None:  # every shop on the domain takes a message for "the current run": two fms up
            # runs on one domain both took an order. The others are matched within moments of the first: wait until
            # the count has held for 1 s (at most 3 s)
            shops, since, give_up = pub.get_subscription_count(), time.monotonic(), time.monotonic() + 3.0
            while time.monotonic() < min(deadline, give_up, since + 1.0):
                rclpy.spin_once(node, timeout_sec=0.05)
                if pub.get_subscription_count() != shops:
                    shops, since = pub.get_subscription_count(), time.monotonic()
            if shops > 1:
                return EXIT_BAD_INPUT, (f"{shops} nodes listen on {topic} (shops of several runs on this domain?) and "
                                        f"each would take this {kind}: name its run with --run-id (fms up prints the "
                                        "run id); nothing was sent")
        pub.publish(String(data=text))
        sent = time.monotonic()
        other_runs: list[str] = []  # refusals of shops of other runs (a message for one run, several on the domain)
        while time.monotonic() < deadline:
            for incoming, (accepted, line) in _heard_answers(node, heard, kind, msg, text):
                if not accepted and incoming.get("code") == "unknown_run":
                    other_runs.append(line)  # the run's own shop answers for it (the first answer was taken)
                    continue
                if accepted and msg.get("run_id") is None:
                    return _only_taker(node, heard, kind, msg, text, incoming["run_id"], line)
                return (EXIT_OK if accepted else EXIT_FAILED), line
            # every shop runs another run (counted once the others have had 2 s to be matched: the run's own shop may
            # be found after another's refusal came)
            if other_runs and time.monotonic() - sent > 2.0 and len(other_runs) >= pub.get_subscription_count():
                return EXIT_FAILED, other_runs[0]
        if other_runs and len(other_runs) >= pub.get_subscription_count():  # no shop of the run: the refusal says so
            return EXIT_FAILED, other_runs[0]
        # (a listener that did not refuse may be the run's own shop, slow to answer: a paced one answers with its next
        # step; its answer was reported as the other run's refusal, "this shop runs 'other'")
        also = f" (shops of other runs refused it: {len(other_runs)})" if other_runs else ""
        return EXIT_FAILED, f"sent {kind} {msg[f'{kind}_id']}, but the shop did not answer within {timeout:g} s{also}"
    finally:
        stop.restore()
        node.destroy_node()
        rclpy.try_shutdown()


def cmd_send(a: argparse.Namespace) -> int:
    """``fms send ...`` (see the module docstring); returns the exit code."""
    from .up import rclpy_missing

    if not a.timeout > 0 or a.timeout == float("inf"):
        raise SendError(f"--timeout must be a positive number of seconds, got {a.timeout:g}")
    kind, msg = build(a)
    if a.domain_id is not None:
        if not 0 <= a.domain_id <= 232:
            raise SendError(f"--domain-id must be in 0..232, got {a.domain_id}")
        os.environ["ROS_DOMAIN_ID"] = str(a.domain_id)
    else:
        env = os.environ.get("ROS_DOMAIN_ID")
        if not env:
            raise SendError("give the shop's ROS domain: --domain-id N or ROS_DOMAIN_ID (fms up prints "
                            "ROS_DOMAIN_ID=N when it starts)")
        try:  # abc was an RCLError traceback, 300 Fast DDS's colours on stdout, -5 a wait for the whole --timeout
            domain = int(env)
        except ValueError:
            raise SendError(f"ROS_DOMAIN_ID must be an integer, got {env!r}") from None
        if not 0 <= domain <= 232:
            raise SendError(f"ROS_DOMAIN_ID must be in 0..232, got {domain}")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    missing = rclpy_missing()
    if missing:
        raise SendError(missing)
    code, line = exchange(kind, msg, a.timeout)
    print(line if code == EXIT_OK else f"fms send: {line}", file=sys.stdout if code == EXIT_OK else sys.stderr)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fms_dispatch.send ...``: the same as ``fms send`` without the ``fms`` CLI."""
    p = argparse.ArgumentParser(prog="fms send", description=__doc__.splitlines()[0])
    _add_arguments(p)
    a = p.parse_args(argv)
    try:
        return cmd_send(a)
    except SendError as exc:
        print(f"fms send: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("fms send: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
