"""The keyframes' places: the relocalization index (relocalization.py) kept up to date with the keyframes, and the
map checked against itself as each keyframe enters it (map_check.py).

Indexing a keyframe (ORB, 12-15 ms for 640 x 480) and checking it (PnP against the older keyframes, a few ms per
candidate) is work a tracker cannot spend while a frame waits. It is done in units (`index_next`: one keyframe's
features, or one candidate of its check), in the lock-step system when the front end asks (before relocalizing, or
when MAX_UNINDEXED keyframes wait), in the pipelined runtime by the mapping process between its steps. There the
tracker keeps a replica: the mapper sends each keyframe's features and check (`Indexed`), which the replica takes
as they are (`take`), so that a lost camera is found against every indexed keyframe without the tracker having
extracted a feature.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import RelocalizationConfig
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.tracking.map_check import MapCheck, check_map
from eslam_core.tracking.relocalization import KeyframeDatabase, KeyframeEntry

log = logging.getLogger("eslam")

MAX_UNINDEXED = 2  # new keyframes waiting for relocalization features (see KeyframePlaces.remember)


@dataclass(frozen=True)
class Indexed:
    """A keyframe's features, and the check of the map it made (None: no older keyframe placed it)."""
    entry: KeyframeEntry
    check: Optional[MapCheck]


class KeyframePlaces:
    def __init__(self, cfg: RelocalizationConfig, intr: Intrinsics, seed: int = 0, publish: bool = False,
                 keep_checks: bool = False):
        self.cfg, self.intr, self.publish = cfg, intr, publish
        # With `keep_checks`: every check that placed a keyframe, since `take_checks` (loop closure's candidates).
        self.checks: Optional[list[MapCheck]] = [] if keep_checks else None
        self.db = KeyframeDatabase(cfg, seed)
        self.unindexed: list[Keyframe] = []  # keyframes not in `db` yet (see remember)
        self.check: Optional[MapCheck] = None  # the newest keyframe placed by older ones
        self.done: list[Indexed] = []  # with `publish`: indexed since `take_done` (what a replica is sent)
        self._checking = None  # the check in progress: a generator, one candidate per step
        self._checked: Optional[KeyframeEntry] = None  # its keyframe's entry
        self._loaded: set[int] = set()  # a loaded map's keyframes: indexed unchecked, the vocabulary after the last

    def __len__(self) -> int:
        return len(self.db)

    def remember(self, kf: Keyframe) -> None:
        """A new keyframe. Its features are extracted later (`index_next`, when the caller is idle, or before the
        next relocalization); at most MAX_UNINDEXED wait: a caller that is never idle indexes them here."""
        self.unindexed.append(kf)
        while len(self.unindexed) > MAX_UNINDEXED:
            self.index_next()

    def start_lost(self, keyframes) -> None:
        """A loaded map's keyframes (those with every pixel: a reduced keyframe is too coarse for ORB), indexed
        when first needed; they were checked when they were made."""
        self.unindexed = [kf for kf in keyframes if kf.stride == 1]
        self._loaded = {kf.number for kf in self.unindexed}

    @property
    def idle_work(self) -> bool:
        """Keyframes wait for indexing, or a check for its next step (`index_next`)."""
        return bool(self.unindexed) or self._checking is not None

    def index_next(self) -> bool:
        """One unit of the work (a few to 15 milliseconds): index the oldest keyframe waiting for it, or take one
        step of the newest keyframe's check; False if nothing waits."""
        if self._checking is not None:
            try:
                next(self._checking)
            except StopIteration as done:
                self._checking = None
                self._note(done.value)
                if self.publish:
                    self.done.append(Indexed(self._checked, done.value))
            return True
        if not self.unindexed:
            return False
        kf = self.unindexed.pop(0)
        self.db.add(kf.number, kf.rgb.numpy(), kf.depth_image().numpy(), kf.pose, self.intr)
        if kf.number in self._loaded:
            self._loaded.discard(kf.number)
            if not self._loaded:  # a loaded map: its words, before the first query
                self.db.build_vocabulary()
        else:  # (a check that finds no older keyframe still ends in `done`, as None)
            self._checked = self.db.entries[kf.number]
            self._checking = check_map(self.db, kf.number, kf.pose.double().numpy(), self.intr, self.cfg)
        return True

    def take(self, indexed: Indexed) -> None:
        """A keyframe indexed elsewhere (the pipelined runtime's mapper): its features and its check as they are."""
        self.db.insert(indexed.entry)
        self._note(indexed.check)

    def take_done(self) -> list[Indexed]:
        done, self.done = self.done, []
        return done

    def _note(self, check: Optional[MapCheck]) -> None:
        if check is not None:
            if check.disagrees:
                log.warning("%s", check.reason)
            self.check = check
            if self.checks is not None:
                self.checks.append(check)

    def take_checks(self) -> list[MapCheck]:
        checks, self.checks = self.checks or [], [] if self.checks is not None else None
        return checks

    @property
    def disagreement(self) -> Optional[MapCheck]:
        """The newest check, where it found the map disagreeing with itself (else None)."""
        return self.check if self.check is not None and self.check.disagrees else None

    def forget(self, numbers) -> None:
        """Keyframes the map's store dropped (as redundant or over its budget) are not relocalized against: the
        index stays the size of the store, not of the time spent."""
        dropped = {int(n) for n in numbers}
        self.unindexed = [kf for kf in self.unindexed if kf.number not in dropped]
        self._loaded -= dropped
        for number in dropped:
            self.db.remove(number)

    def refine(self, poses: dict) -> None:
        """Mapping refined these keyframes' poses (number -> pose): their features move with them."""
        waiting = {kf.number: kf for kf in self.unindexed}
        for number, pose in poses.items():
            if int(number) in waiting:
                waiting[int(number)].pose = torch.as_tensor(pose).float()
            if int(number) in self.db.entries:
                self.db.set_pose(int(number), pose)

    def relocalize(self, rgb, depth):
        """The camera pose of a frame from the indexed keyframes (KeyframeDatabase.relocalize), every waiting
        keyframe indexed first."""
        while self.index_next():
            pass
        return self.db.relocalize(rgb, depth, self.intr) if len(self.db) else None
