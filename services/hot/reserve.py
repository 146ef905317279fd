"""Space held back on the data disk, so a full disk never leaves the node unable to start.

The hot-tier guard refuses new data below FLEET_MIN_FREE_BYTES and promotion refuses to seal below
FLEET_RESERVE_BYTES, but other programs can still fill the disk. The embedded catalog must then
still be able to open and write (a catalog that cannot write invalidates itself, and a node that
cannot open it cannot start). So the node keeps a file of FLEET_RESERVE_BYTES of allocated blocks
in its data dir; when it finds the disk full, it deletes that file to give the catalog room, says
so, and allocates it again once the disk has room.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

log = logging.getLogger(__name__)

RESERVE_FILE = "reserved-space"
FULL_BELOW = 16 * 1024 * 1024  # free bytes under which the disk counts as full


class DiskReserve:
    def __init__(self, data_dir: Path, size: int) -> None:
        self.path = data_dir / RESERVE_FILE
        self.size = size

    @property
    def held(self) -> bool:
        return self.path.exists()

    def free(self) -> int:
        return shutil.disk_usage(self.path.parent).free

    def release_if_full(self) -> bool:
        """Delete the reserve when the disk is full; returns whether it was released."""
        if not self.held or self.free() >= FULL_BELOW:
            return False
        self.path.unlink(missing_ok=True)
        log.warning(
            "the data disk is full: released the %d bytes held in reserve (%s) so the catalog can "
            "work; new data is refused until space is freed or runs are promoted",
            self.size,
            self.path,
        )
        return True

    def ensure(self) -> bool:
        """Hold the reserve if it is missing and the disk has room for it and as much again; returns
        whether it is held afterwards."""
        if self.size <= 0 or self.held:
            return self.held
        if self.free() < 2 * self.size:
            return False
        tmp = self.path.with_name(RESERVE_FILE + ".tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                os.posix_fallocate(fd, 0, self.size)  # real blocks, not a sparse file
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            log.warning("could not hold %d bytes in reserve at %s: %s", self.size, self.path, exc)
            return False
        return True
