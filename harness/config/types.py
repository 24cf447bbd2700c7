"""Field types shared by the config models (``hil.harness.config.model`` and its sections)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BeforeValidator, ConfigDict
from pydantic_core import PydanticCustomError


def _reject_bool(value: Any) -> Any:
    # pydantic's lax mode reads true/false as 1/0; in a config that is always a typo.
    if isinstance(value, bool):
        raise PydanticCustomError("bool_not_number", "a number, not true/false")
    return value


Int = Annotated[int, BeforeValidator(_reject_bool)]
Float = Annotated[float, BeforeValidator(_reject_bool)]

MODEL_CONFIG = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
