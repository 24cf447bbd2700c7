"""Shared fixtures. MuJoCo's GL backend is fixed when ``mujoco`` is first imported,
so it is chosen here, before any test module imports the simulator."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from hil.harness.vocab.events import EVENT_SCHEMA
from hil.scenarios.gl import select_backend

GL_BACKEND = select_backend()


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
