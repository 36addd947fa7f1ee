"""The simulation: a MuJoCo world with its Warp meshes (``world``), the car (``vehicle``), moving actors
(``actors``), the simulated LiDAR (``lidar``), one drive frame by frame (``drive``), the scene's true
geometry (``geometry``) and pictures of it (``render``)."""
