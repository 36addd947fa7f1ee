"""Recordings in and out: one way in for every source (``sources.open_source``, the ``FrameSource``
protocol), the KITTI-layout folder (``kitti``), ROS 1 / ROS 2 bags and MCAP (``rosbag``, decoding in
``pointcloud2``; the ``[ros]`` extra), folders of ``.pcd``/``.ply`` scans (``scanfolder``), KITTI ``.bin``
scans (``scanio``), conversion between them (``convert``) and LiDAR odometry from the scans
(``lidar_odometry``, kiss-icp). It imports the foundation and the sensing core (``rangemcl.common``,
``se2``, ``sensors``), never the maps or the localizer."""
