"""KITTI odometry registration pairs: calibration and pose files, the standard pair lists, ICP-refined ground truth.

Layout of ``root`` (the official KITTI odometry download, plus the standard pair lists)::

    root/
      sequences/NN/velodyne/FFFFFF.bin   LiDAR scans, float32 records (x, y, z, reflectance), metres
      sequences/NN/calib.txt             line ``Tr: <12 values>`` = velodyne -> camera 0, 3x4 row-major
      poses/NN.txt                       camera-0 poses in the world frame, one 3x4 row-major line per frame
      pairs/{train,val,test}.json        optional: the FCGF/GeoTransformer pair lists, entries with seq_id, frame0,
                                         frame1 and transform (4x4, maps frame1's scan into frame0's scan)

Modules (everything public is re-exported here, e.g. ``from lcreg.data.kitti import KITTIOdometryDataModule``):

* :mod:`~lcreg.data.kitti.layout`: paths of the layout, which scans exist, the error text for missing files;
* :mod:`~lcreg.data.kitti.io`: ``calib.txt``, ``poses/NN.txt`` and json parsing, and the relative LiDAR pose
  ``T_j_i = inv(Tr) inv(P_j) P_i Tr`` (:func:`relative_lidar_pose`, maps points of scan ``i`` into scan ``j``);
* :mod:`~lcreg.data.kitti.selection`: the ``"standard"`` FCGF chain (reproduces the 1,358 / 180 / 555 json
  pairs from the poses) and the ``"all"`` selection (every pair at least ``min_distance`` apart);
* :mod:`~lcreg.data.kitti.icp`: :func:`refine_with_icp` (FCGF's point-to-point ICP, correctly composed) and the
  bounded cache of refined pairs;
* :mod:`~lcreg.data.kitti.pairs`: :func:`kitti_pairs`, the pairs of a split with their ground truth (json
  transforms as they are, or pose-derived and ICP-refined);
* :mod:`~lcreg.data.kitti.datamodule`: :class:`KITTIOdometryDataModule`.
"""

from __future__ import annotations

from lcreg.data.kitti.datamodule import KITTIOdometryDataModule
from lcreg.data.kitti.icp import refine_with_icp
from lcreg.data.kitti.io import read_calib_velo_to_cam, read_poses, relative_lidar_pose
from lcreg.data.kitti.layout import EXPECTED_LAYOUT, scan_path
from lcreg.data.kitti.pairs import kitti_pairs
from lcreg.data.kitti.selection import EXCLUDED_PAIRS, KITTI_SPLITS, all_pairs, standard_chain_pairs

__all__ = [
    "EXCLUDED_PAIRS",
    "EXPECTED_LAYOUT",
    "KITTI_SPLITS",
    "KITTIOdometryDataModule",
    "all_pairs",
    "kitti_pairs",
    "read_calib_velo_to_cam",
    "read_poses",
    "refine_with_icp",
    "relative_lidar_pose",
    "scan_path",
    "standard_chain_pairs",
]
