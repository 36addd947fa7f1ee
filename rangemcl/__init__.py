"""rangemcl: range-image Monte Carlo localization of a LiDAR in a triangle-mesh map."""

__version__ = "0.1.0"
