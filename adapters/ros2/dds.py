"""Cyclone DDS for the ``ros2`` transport, both halves: a participant on an explicitly
configured domain, readers and writers with ROS 2's topic and type names, samples
written and taken as raw CDR (hil.adapters.ros2.cdr), and the writers of a topic
named for people.

Cyclone keeps domains per process: a domain id can be created once. ``Participant``
shares one ``Domain`` per id among the participants of this process (counted; the
last one out deletes it) and refuses a second, different configuration for an id
that is open.

Raises: :class:`hil.common.errors.TransportError` when Cyclone refuses an operation;
:class:`hil.common.errors.ConfigError` for a domain opened twice with two configurations.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from hil.adapters.ros2 import cdr as ros2_cdr
from hil.adapters.ros2.msgs import dds_name
from hil.adapters.ros2.options import Durability, History, QosProfile, Reliability, check_domain, dds_topic
from hil.common.errors import ConfigError, TransportError

try:
    from cyclonedds._clayer import ddspy_take, ddspy_write
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsParticipant, BuiltinTopicDcpsPublication
    from cyclonedds.core import DDSException, Policy, Qos
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the ros2 transport needs Cyclone DDS: pip install cyclonedds==11.0.1") from _err

MAX_BLOCKING_NS = 100_000_000  # a reliable write waits at most this for room (then it fails, counted)
_ANY_STATE = 0xFFFF  # sample, view and instance state: any


class _Domains:
    """This process's Cyclone domains: id -> (Domain, its configuration, users)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open: dict[int, tuple[Domain, str, int]] = {}

    def acquire(self, domain_id: int, config: str) -> None:
        with self._lock:
            got = self._open.get(domain_id)
            if got is not None:
                if got[1] != config:
                    raise ConfigError(f"DDS domain {domain_id} is already open in this process with another "
                                      f"Cyclone configuration; use another domain_id")
                self._open[domain_id] = (got[0], config, got[2] + 1)
                return
            try:
                self._open[domain_id] = (Domain(domain_id, config), config, 1)
            except DDSException as err:
                raise TransportError(f"Cyclone DDS refused domain {domain_id}: {err}") from err

    def release(self, domain_id: int) -> None:
        with self._lock:
            got = self._open.pop(domain_id, None)
            if got is None:
                return
            if got[2] > 1:
                self._open[domain_id] = (got[0], got[1], got[2] - 1)
            else:
                got[0].__del__()  # deletes the domain now, not when the collector gets to it


_DOMAINS = _Domains()  # Cyclone's domains are process-wide; so is their bookkeeping


def qos_of(profile: QosProfile) -> Qos:
    """Cyclone's ``Qos`` for a ROS 2 QoS profile."""
    rel = (Policy.Reliability.Reliable(max_blocking_time=MAX_BLOCKING_NS)
           if profile.reliability == Reliability.RELIABLE else Policy.Reliability.BestEffort)
    hist = Policy.History.KeepLast(profile.depth) if profile.history == History.KEEP_LAST else Policy.History.KeepAll
    dur = Policy.Durability.TransientLocal if profile.durability == Durability.TRANSIENT_LOCAL \
        else Policy.Durability.Volatile
    return Qos(rel, hist, dur)


@dataclass(frozen=True)
class WriterInfo:
    """A DDS writer seen in discovery: its GUID, its participant's GUID, topic and
    type names, and who it is (entity name, process name and pid, host)."""

    guid: str
    participant: str
    topic: str
    type_name: str
    who: str


class Participant:
    """One DomainParticipant on ``domain_id`` with Cyclone configuration ``config``
    (hil.adapters.ros2.options.cyclone_xml); ``name`` is its DDS entity name. A context
    manager; ``close()`` is idempotent.

    Raises:
        ConfigError: bad domain id, or the domain is open here with another configuration.
        TransportError: Cyclone refused to create it.
    """

    def __init__(self, *, domain_id: int, config: str, name: str) -> None:
        self.domain_id = check_domain(domain_id)
        _DOMAINS.acquire(domain_id, config)
        self._closed = False
        try:
            self.dp = DomainParticipant(domain_id, qos=Qos(Policy.EntityName(name)))
            self._pubs = BuiltinDataReader(self.dp, BuiltinTopicDcpsPublication)
            self._parts = BuiltinDataReader(self.dp, BuiltinTopicDcpsParticipant)
        except DDSException as err:
            _DOMAINS.release(domain_id)
            raise TransportError(f"Cyclone DDS refused a participant on domain {domain_id}: {err}") from err
        self._topics: dict[str, Topic[Any]] = {}
        self._who: dict[str, str] = {}

    def _topic(self, ros_topic: str, cls: type[IdlStruct]) -> Topic[Any]:
        name = dds_topic(ros_topic)
        topic = self._topics.get(name)
        if topic is None:
            try:
                topic = self._topics[name] = Topic(self.dp, name, cls)
            except DDSException as err:
                raise TransportError(f"Cyclone DDS refused topic {name!r} ({dds_name(cls)}): {err}") from err
        return topic

    def writer(self, ros_topic: str, cls: type[IdlStruct], profile: QosProfile) -> DataWriter[Any]:
        """A writer of ``cls`` on ROS 2 topic ``ros_topic``."""
        try:
            return DataWriter(self.dp, self._topic(ros_topic, cls), qos=qos_of(profile))
        except DDSException as err:
            raise TransportError(f"Cyclone DDS refused a writer on {ros_topic!r}: {err}") from err

    def reader(self, ros_topic: str, cls: type[IdlStruct], profile: QosProfile) -> DataReader[Any]:
        """A reader of ``cls`` on ROS 2 topic ``ros_topic``."""
        try:
            return DataReader(self.dp, self._topic(ros_topic, cls), qos=qos_of(profile))
        except DDSException as err:
            raise TransportError(f"Cyclone DDS refused a reader on {ros_topic!r}: {err}") from err

    def writers(self) -> list[WriterInfo]:
        """Every writer discovered so far, gone ones included (not this participant's)."""
        self._learn_participants()
        own = str(self.dp.guid)
        out = []
        for s in self._pubs.read(N=4096):
            if str(s.participant_key) == own:
                continue
            part = str(s.participant_key)
            out.append(WriterInfo(str(s.key), part, str(s.topic_name), str(s.type_name),
                                  self._who.get(part, f"participant {part}")))
        return out

    def writer_name(self, reader: DataReader[Any], handle: int) -> str:
        """Who wrote with publication ``handle`` (matched to ``reader``), for messages."""
        try:
            ep = reader.get_matched_publication_data(handle)
        except DDSException:
            ep = None
        if ep is None:
            return f"writer {handle:#x} (no longer matched)"
        self._learn_participants()
        part = str(ep.participant_key)
        return f"writer {ep.key} of {self._who.get(part, f'participant {part}')}"

    def _learn_participants(self) -> None:
        for s in self._parts.take(N=256):
            self._who[str(s.key)] = _describe(s.qos)

    def close(self) -> None:
        if getattr(self, "_closed", True):
            return
        self._closed = True
        try:
            self.dp.__del__()  # the participant and everything in it, now
        finally:
            _DOMAINS.release(self.domain_id)

    def __enter__(self) -> Participant:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _describe(qos: Any) -> str:
    """'name (process pid N on host)' from a participant's discovered QoS."""
    props: dict[str, str] = {}
    name = ""
    for p in qos or ():
        if getattr(p, "__scope__", "") == "EntityName":
            name = str(p.name)
        key = getattr(p, "key", None)
        if isinstance(key, str):
            props[key] = str(getattr(p, "value", ""))
    proc = props.get("__ProcessName", "?")
    where = f"{proc} pid {props.get('__Pid', '?')} on {props.get('__Hostname', '?')}"
    return f"{name} ({where})" if name else where


def handle_of(handle: int) -> int:
    """An instance handle as one unsigned number (matched-writer lists give them
    signed, sample infos unsigned)."""
    return int(handle) & 0xFFFF_FFFF_FFFF_FFFF


def matched_writers(reader: DataReader[Any]) -> set[int]:
    """The writers matched to ``reader`` now (``handle_of`` form)."""
    return {handle_of(h) for h in reader.get_matched_publications()}


def write(writer: DataWriter[Any], msg: IdlStruct) -> None:
    """Write ``msg`` as CDR (our encoder; Cyclone checks the bytes against the type).

    Raises:
        TransportError: Cyclone refused or timed out (a reliable writer with no room).
    """
    ret = ddspy_write(writer._ref, ros2_cdr.encode(msg, pad=True))
    if ret < 0:
        raise TransportError(f"DDS write on {writer.topic.name!r} failed: {DDSException(ret, '')}".rstrip(": "))


def take(reader: DataReader[Any], n: int = 64) -> list[tuple[bytes, Any]]:
    """Up to ``n`` samples waiting in ``reader``: (CDR bytes, Cyclone's SampleInfo),
    valid ones only (the others mark instance state changes).

    Raises:
        TransportError: Cyclone refused the take.
    """
    got = ddspy_take(reader._ref, _ANY_STATE, n)
    if isinstance(got, int):
        raise TransportError(f"DDS take on {reader.topic.name!r} failed: {DDSException(got, '')}")
    return [(data, info) for data, info in got if info.valid_data]


__all__ = ["MAX_BLOCKING_NS", "Participant", "WriterInfo", "handle_of", "matched_writers", "qos_of", "take", "write"]
