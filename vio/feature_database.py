"""The MSCKF feature database (open_vins ``FeatureDatabase``): observations per frame, camera and id.

Storage is ``camera x slot x column`` arrays: a slot holds one frame (keyed by its camera time, the clone
key), a column one feature id; slots and columns are recycled. Observations are undistorted normalized
coordinates of their own camera (cam0, and cam1 on a stereo rig).
"""

from __future__ import annotations

import numpy as np


class FeatureDatabase:
    """Observations per (frame time, camera, feature id) in fixed arrays.

    Args:
        max_frames: Frame slots (the clone window plus slack).
        initial_features: Initial column capacity (doubles when full).
        num_cameras: Cameras of the rig (1 mono, 2 stereo).
    """

    def __init__(self, max_frames: int, initial_features: int = 512, num_cameras: int = 1) -> None:
        """Create an empty database."""
        if num_cameras not in (1, 2):
            raise ValueError(f"FeatureDatabase: num_cameras must be 1 or 2, got {num_cameras}")
        self.num_cameras = num_cameras
        self._slot_t = np.full(max_frames, np.nan)
        self._xy = np.zeros((num_cameras, max_frames, initial_features, 2))
        self._has = np.zeros((num_cameras, max_frames, initial_features), dtype=bool)
        self._col_id = np.full(initial_features, -1, dtype=np.int64)
        self._id_to_col: dict[int, int] = {}

    @property
    def frame_times(self) -> np.ndarray:
        """Stored frame times (s), sorted, shape (S,)."""
        t = self._slot_t[np.isfinite(self._slot_t)]
        return np.sort(t)

    def _slot_of(self, t_s: float) -> int | None:
        hit = np.nonzero(self._slot_t == t_s)[0]
        return int(hit[0]) if len(hit) else None

    def _grow(self) -> None:
        c = self._col_id.shape[0]
        self._xy = np.concatenate([self._xy, np.zeros_like(self._xy)], axis=2)
        self._has = np.concatenate([self._has, np.zeros_like(self._has)], axis=2)
        self._col_id = np.concatenate([self._col_id, np.full(c, -1, dtype=np.int64)])

    def add(self, t_s: float, ids: np.ndarray, xy_norm: np.ndarray, cam: int = 0) -> None:
        """Store one camera's observations of the frame at ``t_s`` (the oldest frame is evicted when full).

        Args:
            t_s: Frame time (s), the clone key.
            ids: Feature ids, shape (M,).
            xy_norm: Undistorted normalized coordinates in camera ``cam``, shape (M, 2).
            cam: Camera index (0 or 1).
        """
        if not 0 <= cam < self.num_cameras:
            raise ValueError(f"FeatureDatabase.add: camera {cam} outside 0..{self.num_cameras - 1}")
        slot = self._slot_of(t_s)
        if slot is None:
            free = np.nonzero(~np.isfinite(self._slot_t))[0]
            if len(free) == 0:
                self.remove_frame(float(np.nanmin(self._slot_t)))
                free = np.nonzero(~np.isfinite(self._slot_t))[0]
            slot = int(free[0])
            self._slot_t[slot] = t_s
            self._has[:, slot] = False
        id_list = np.asarray(ids, dtype=np.int64).ravel().tolist()
        get = self._id_to_col.get
        cols = np.fromiter((get(fid, -1) for fid in id_list), dtype=np.int64, count=len(id_list))
        new = np.flatnonzero(cols < 0)
        if len(new):
            # New ids take the lowest free columns in order of first appearance (one search, not one each).
            new_ids, first = np.unique(np.asarray(id_list)[new], return_index=True)
            new_ids = new_ids[np.argsort(first)]
            free_cols = np.flatnonzero(self._col_id < 0)
            while len(free_cols) < len(new_ids):
                self._grow()
                free_cols = np.flatnonzero(self._col_id < 0)
            take = free_cols[: len(new_ids)]
            self._col_id[take] = new_ids
            self._id_to_col.update(zip(new_ids.tolist(), take.tolist(), strict=True))
            cols[new] = [self._id_to_col[fid] for fid in np.asarray(id_list)[new].tolist()]
        self._xy[cam, slot, cols] = xy_norm
        self._has[cam, slot, cols] = True

    def _active_cols(self) -> np.ndarray:
        return np.nonzero(self._col_id >= 0)[0]

    def features_lost(self, t_s: float) -> np.ndarray:
        """Ids with observations but none (in any camera) at time ``t_s`` (tracks that ended before it)."""
        cols = self._active_cols()
        slot = self._slot_of(t_s)
        if slot is None:
            return self._col_id[cols]
        return self._col_id[cols[~self._has[:, slot, cols].any(axis=0)]]

    def features_seen_at(self, t_s: float) -> np.ndarray:
        """Ids observed (in any camera) at time ``t_s``."""
        slot = self._slot_of(t_s)
        if slot is None:
            return np.zeros(0, dtype=np.int64)
        cols = self._active_cols()
        return self._col_id[cols[self._has[:, slot, cols].any(axis=0)]]

    def track_lengths(self, ids: np.ndarray) -> np.ndarray:
        """Number of stored observations of each id over all cameras (0 for unknown ids), shape (F,)."""
        cols = np.array([self._id_to_col.get(int(i), -1) for i in ids], dtype=np.int64)
        valid = self._slot_t == self._slot_t  # finite slots
        if not len(cols):
            return np.zeros(0, int)
        counts = self._has[:, :, np.maximum(cols, 0)][:, valid].sum(axis=(0, 1))
        return np.where(cols >= 0, counts, 0)

    def observations(self, ids: np.ndarray, times: np.ndarray, cam: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Observations of ``ids`` at ``times`` in camera ``cam``: xy (F, K, 2) and mask (F, K)."""
        cols = np.array([self._id_to_col.get(int(i), -1) for i in ids], dtype=np.int64)
        F, K = len(ids), len(times)
        xy = np.zeros((F, K, 2))
        mask = np.zeros((F, K), dtype=bool)
        # The slot of each time (at most one: times are unique keys), then one gather for all of them.
        hit = np.asarray(times, dtype=float)[:, None] == self._slot_t[None, :]
        ks, rows = np.flatnonzero(hit.any(axis=1)), np.flatnonzero(cols >= 0)
        if len(ks) and len(rows):
            slots = hit[ks].argmax(axis=1)
            sub = np.ix_(rows, ks)
            xy[sub] = self._xy[cam][slots[None, :], cols[rows, None]]
            mask[sub] = self._has[cam][slots[None, :], cols[rows, None]]
        return xy, mask

    def remove_features(self, ids: np.ndarray) -> None:
        """Delete every observation of ``ids``."""
        pop = self._id_to_col.pop
        cols = [c for c in (pop(int(fid), None) for fid in np.asarray(ids).ravel().tolist()) if c is not None]
        if cols:  # one scatter for all of them
            self._has[:, :, cols] = False
            self._col_id[cols] = -1

    def remove_frame(self, t_s: float) -> None:
        """Delete the frame at ``t_s`` and every feature left without observations."""
        slot = self._slot_of(t_s)
        if slot is None:
            return
        self._has[:, slot] = False
        self._slot_t[slot] = np.nan
        cols = self._active_cols()
        empty = cols[~self._has[:, :, cols].any(axis=(0, 1))]
        self.remove_features(self._col_id[empty])

    def cleanup_older_than(self, t_s: float) -> None:
        """Delete every frame older than ``t_s``."""
        for t in self.frame_times[self.frame_times < t_s]:
            self.remove_frame(float(t))

    @property
    def num_features(self) -> int:
        """Number of feature ids stored."""
        return len(self._id_to_col)
