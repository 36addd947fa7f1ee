"""The simulation: a MuJoCo world with its Warp meshes (``world``), the car (``vehicle``), moving actors
(``actors``), the simulated LiDAR (``lidar``), one drive frame by frame (``drive``), the scene's true
geometry (``geometry``) and pictures of it (``render``)."""

# the simulated LiDAR: every surface returns every ray (ideal), or materials, angles and range decide
# returns, noise and intensity (realistic; simbed.sim.lidar); light here, so that the command line's
# options can name the default without loading the simulator
SENSOR_MODELS = ("ideal", "realistic")
DEFAULT_SENSOR_MODEL = "ideal"  # every command's, drive's and suite's unless one names another
