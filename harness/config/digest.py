"""A config's digest (``config_hash`` in a run's metadata and summary): sha256 of its
canonical JSON, computed alike from a loaded config and from a run folder's
``config.json`` (standard library only, so readers of run folders need no config model).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

# Fields added after runs first recorded their config hash, left out of it while at
# their default: a config that does not use one hashes as it did before it existed,
# so ``hil compare`` against an older baseline notes no difference where there is none.
HASH_NEUTRAL_DEFAULTS: dict[tuple[str, str], Any] = {("camera", "antialias"): 4}


def digest(doc: Mapping[str, Any]) -> str:
    """sha256 hex digest of ``doc`` (a config as JSON: ``dump_config``'s, or a
    ``config.json``) as canonical JSON (sorted keys, no spaces), ``HASH_NEUTRAL_DEFAULTS``
    left out at their defaults; ``doc`` is not changed."""
    canon = dict(doc)
    for (section, key), default in HASH_NEUTRAL_DEFAULTS.items():
        part = canon.get(section)
        if isinstance(part, dict) and key in part and part[key] == default:
            canon[section] = {k: v for k, v in part.items() if k != key}
    text = json.dumps(canon, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
