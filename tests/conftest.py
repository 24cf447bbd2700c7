"""Shared fixtures. MuJoCo's GL backend is fixed when ``mujoco`` is first imported,
so it is chosen here, before any test module imports the simulator."""

from __future__ import annotations

import json
import multiprocessing
import os
from collections import defaultdict
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import jsonschema
import pytest

from hil.harness.vocab.events import EVENT_SCHEMA
from hil.scenarios.gl import select_backend

GL_BACKEND = select_backend()
T = TypeVar("T")


def in_child_processes(fn: Callable[..., T], calls: Sequence[tuple[Any, ...]], *, at_most: int = 4) -> list[T]:
    """``[fn(*args) for args in calls]``, computed in child processes, as many at once as
    this machine has cores (``at_most``): the results, in the calls' order, are what the
    loop would return. Only for deterministic, CPU-bound work whose results do not depend
    on timing (lockstep runs, in-process closed loops): never for real-time runs, which
    would load each other. ``fn`` and its arguments must be importable by name (a
    module-level function); the children are spawned, not forked, so nothing of this
    process (threads, GL contexts) is copied into them. A failure in a child is raised here."""
    workers = max(1, min(at_most, len(os.sched_getaffinity(0)), len(calls)))
    if workers == 1:
        return [fn(*args) for args in calls]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(fn, *zip(*calls)))


def read_mcap(path: Path) -> dict[str, list[tuple[Any, Any]]]:
    """All messages of an MCAP file by topic: (message record, decoded JSON)."""
    from mcap.reader import make_reader

    out: dict[str, list[tuple[Any, Any]]] = defaultdict(list)
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            assert schema is not None and schema.encoding == "jsonschema", channel.topic
            d = json.loads(message.data)
            if channel.topic == "/events":  # every event, in every test that reads one, against its one schema
                assert json.loads(schema.data)["required"] == EVENT_SCHEMA["required"], "not the event schema"
                jsonschema.validate(d, json.loads(schema.data))
            out[channel.topic].append((message, d))
    return out


@pytest.fixture
def gl_backend() -> str:
    return GL_BACKEND
