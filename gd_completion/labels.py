"""The vehicle labels the package completes and their ids in the output's `label` field."""
from __future__ import annotations

LABEL_IDS: dict[str, int] = {"car": 1, "van": 2, "truck": 3}
DEFAULT_LABELS: tuple[str, ...] = ("car", "van", "truck")
