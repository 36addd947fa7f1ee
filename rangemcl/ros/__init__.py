"""ROS bags and MCAP in and out (the optional extra ``[ros]``): PointCloud2 decoding in plain numpy
(:mod:`rangemcl.ros.pointcloud2`), bags as sequences and drives as bags (:mod:`rangemcl.ros.bag`)."""
