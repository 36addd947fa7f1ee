"""The fields every recording reader fills (:class:`Recording`), written once: the KITTI folder's
:class:`~rangemcl.datasets.kitti.Sequence`, the bags' :class:`~rangemcl.datasets.rosbag.BagSequence` and
the scan folders' :class:`~rangemcl.datasets.scanfolder.ScanFolderSequence` add where their scans come
from and how they are read (the protocol they all follow: :class:`rangemcl.datasets.sources.FrameSource`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(kw_only=True)
class Recording:
    """What a recording holds besides its scans; keyword-only, after each reader's own fields.

    ``poses`` and ``odometry`` are LiDAR poses in the world, ``(N, 4, 4)`` float64 (``file @ Tr`` for a
    KITTI folder); ``None`` where the recording has none (likewise ``times`` ``(N,)``, seconds at each
    sweep's end, and ``imu_roll_pitch`` ``(N, 2)``, radians)."""

    poses: np.ndarray | None = None
    times: np.ndarray | None = None
    odometry: np.ndarray | None = None
    imu_roll_pitch: np.ndarray | None = None
    calib_Tr: np.ndarray = field(default_factory=lambda: np.eye(4))  # (4, 4) sensor -> poses' frame
    meta: dict[str, Any] = field(default_factory=dict)
    calib_source: str = "calib.txt"  # where calib_Tr came from: said, never silently assumed
