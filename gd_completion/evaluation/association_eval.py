"""The built-in association of box ids against PandaSet's true track ids (the cuboid uuids, hidden from it)."""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from gd_completion.association import AssociationSettings, BoxAssociator
from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.geometry import box_problem

DEFAULT_LABELS = ("car", "van", "truck")


@dataclass(frozen=True)
class AssociationResult:
    """Agreement of the association with the true ids over consecutive frames of a sequence."""

    frames: int
    boxes: int
    true_links: int     # (frame, next frame) pairs of boxes of the same true track
    kept_links: int     # of those, the association gave both the same id
    links: int          # pairs of boxes the association gave the same id in consecutive frames
    wrong_links: int    # of those, boxes of different true tracks
    purity: float       # share of boxes that carry their true track's most frequent associated id

    @property
    def kept(self) -> float:
        """Share of the true links the association kept."""
        return self.kept_links / self.true_links if self.true_links else float("nan")

    @property
    def wrong(self) -> float:
        """Share of the association's links that join two different true tracks."""
        return self.wrong_links / self.links if self.links else float("nan")


def association_agreement(root: str | Path, *, sensor: int = 0, labels: Sequence[str] = DEFAULT_LABELS,
                          settings: AssociationSettings | None = None) -> AssociationResult:
    """Feed every lidar frame's boxes of `labels` (sensor frame, as the node sees them; ids hidden) to a fresh
    `BoxAssociator` in time order and compare its ids with the cuboids' uuids."""
    sequence = PandaSetSequence(root)
    associator = BoxAssociator(settings)
    per_frame: list[dict[str, int]] = []   # uuid -> associated id
    for index in sequence.frame_indices():
        boxes, _, uuids = sequence.boxes(index, sensor)
        kept = [(b, u) for b, u in zip(boxes, uuids) if b.label in labels and box_problem(b) is None]
        assigned = associator.assign(sequence.stamp_ns(index), [replace(b, instance_id=-1) for b, _ in kept])
        per_frame.append({u: a.instance_id for (_, u), a in zip(kept, assigned)})
    true_links = kept_links = links = wrong = 0
    for now, after in zip(per_frame, per_frame[1:]):
        for uuid, track in now.items():
            if uuid in after:
                true_links += 1
                kept_links += after[uuid] == track
        by_id = {track: uuid for uuid, track in after.items()}
        for uuid, track in now.items():
            if track in by_id:
                links += 1
                wrong += by_id[track] != uuid
    ids_by_uuid: dict[str, Counter] = {}
    for frame in per_frame:
        for uuid, track in frame.items():
            ids_by_uuid.setdefault(uuid, Counter())[track] += 1
    count = sum(len(f) for f in per_frame)
    majority = sum(c.most_common(1)[0][1] for c in ids_by_uuid.values())
    return AssociationResult(len(per_frame), count, true_links, kept_links, links, wrong,
                             majority / count if count else float("nan"))
