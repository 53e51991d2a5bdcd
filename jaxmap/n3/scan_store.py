"""The N3 map's scans of a SLAM run, kept to add a frame again after a loop correction.

    scans = ScanStore(os.path.join(run_dir, "slam_scans"))
    scans.append(PreparedScan(points, normals, image))    # frame len(scans)
    scans[i]                                               # PreparedScan of frame i

Each scan is a `jaxmap.n3.scan.PreparedScan` (sensor frame; about 1.5 MB a frame of KITTI's HDL-64E).
With a directory, each is written there as it comes (`<frame>.pkl`), and only the newest `recent` stay
in memory, so a run holds a few scans whatever its length, and a checkpoint of the run (which pickles
the store) carries the count, not the scans: it costs the same at frame 50 as at frame 3,000. A resumed
run that goes on from an earlier checkpoint than the last files written (kill -9 between two
checkpoints) writes those frames again. Without a directory (tests, a run that is not saved) every scan
stays in memory and is pickled with the store.
"""
from __future__ import annotations

import os
import pickle

from jaxmap.errors import CheckpointError
from jaxmap.n3.scan import PreparedScan


class ScanStore:
    """Frame i -> its `PreparedScan`, for i < len(store) (see the module docstring)."""

    def __init__(self, directory: str | None = None, recent: int = 2):
        self.directory, self.recent = directory, recent
        self._n = 0
        self._held: dict[int, PreparedScan] = {}
        if directory is not None:
            os.makedirs(directory, exist_ok=True)

    def __len__(self) -> int:
        return self._n

    def _path(self, i: int) -> str:
        return os.path.join(self.directory, f"{i:06d}.pkl")

    def append(self, scan: PreparedScan) -> None:
        i = self._n
        if self.directory is not None:
            tmp = self._path(i) + ".tmp"
            with open(tmp, "wb") as f:
                pickle.dump(scan, f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, self._path(i))
            self._held.pop(i - self.recent, None)
        self._held[i] = scan
        self._n = i + 1

    def __getitem__(self, i: int) -> PreparedScan:
        if not 0 <= i < self._n:
            raise IndexError(f"frame {i} of a ScanStore of {self._n}")
        if i in self._held:
            return self._held[i]
        try:
            with open(self._path(i), "rb") as f:
                return pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError) as e:
            raise CheckpointError(f"{self._path(i)}: the scan of frame {i}, needed to map it again, cannot be read "
                                  f"({type(e).__name__}: {e}); start the run again with --overwrite") from None

    def __getstate__(self) -> dict:
        """A checkpoint keeps the count (and, without a directory, the scans)."""
        held = self._held if self.directory is None else {}
        return {"directory": self.directory, "recent": self.recent, "_n": self._n, "_held": held}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
