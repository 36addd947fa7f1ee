"""simbed: the MuJoCo + Warp simulation test bed for LiDAR localization (uses rangemcl's ray casting)."""

__version__ = "0.1.0"
