"""No server paths in API responses: job records (message, error, metrics), progress events and asset manifests
pass through `redact_data` on their way out. A path under the storage folder becomes its storage key
("captures/cap_.../x.png"), one under the data folder, the repository or the home folder loses that prefix, and any
other absolute path keeps only its last component ("…/name"). The records themselves keep the full text for
operators.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path
from typing import Any

from services.core.config import get_settings

REPO = Path(__file__).resolve().parents[1]
# An absolute POSIX path of two or more components, not an API route (/v1/...) nor part of a URL or a word.
ABSOLUTE = re.compile(r"(?<![\w.:/~-])/(?!v1/)(?:[\w.+@-]+/)+[\w.+@-]*")


@lru_cache
def _prefixes() -> tuple[str, ...]:
    st = get_settings()
    found = {str(st.local_root), str(st.data_dir.resolve()), str(REPO), str(Path.home())}
    for p in list(found):
        found.add(str(Path(p).resolve()))
    return tuple(sorted((p.rstrip("/") + "/" for p in found if p not in ("", "/")), key=len, reverse=True))


def redact_text(text: str) -> str:
    if "/" not in text:
        return text
    for prefix in _prefixes():
        text = text.replace(prefix, "")
    return ABSOLUTE.sub(lambda m: "…/" + m.group(0).rstrip("/").rsplit("/", 1)[-1], text)


def redact_data(value: Any) -> Any:
    """`value` (JSON-like) with every string redacted."""
    if isinstance(value, str):
        return redact_text(value)
    if isinstance(value, dict):
        return {k: redact_data(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [redact_data(v) for v in value]
    return value
