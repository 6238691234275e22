"""On-disk LLM response cache: one small JSON file per request.

The key is the SHA-256 of (model, messages, sampling settings), so a rerun
with the same prompts is deterministic and free, an interrupted evaluation
resumes without re-asking, and a published run can be replayed offline by
shipping its cache directory.  Files are written atomically; a corrupt entry
is ignored (and re-requested) with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

from agnostos_mjx.infra.cli import atomic_write

log = logging.getLogger("agnostos_mjx.llm")


class ResponseCache:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    @staticmethod
    def key(model: str, messages: list[dict[str, str]], sampling: dict[str, Any]) -> str:
        blob = json.dumps({"model": model, "messages": messages, "sampling": sampling},
                          sort_keys=True, ensure_ascii=False)
        return hashlib.sha256(blob.encode("utf-8")).hexdigest()

    def _path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.json"

    def get(self, key: str) -> str | None:
        path = self._path(key)
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text(encoding="utf-8"))["text"]
        except (json.JSONDecodeError, KeyError, OSError):
            log.warning("ignoring corrupt LLM cache entry %s", path)
            return None

    def put(self, key: str, text: str) -> None:
        path = self._path(key)
        path.parent.mkdir(exist_ok=True)
        atomic_write(path, json.dumps({"text": text}, ensure_ascii=False))
