"""rangemcl: range-image Monte Carlo localization of a LiDAR in a triangle-mesh map."""

# The package's version is the localizer's (semantic versioning; CHANGELOG.md says what each changed): a
# minor release changes what the localizer computes, a patch release does not. Trial keys and result files
# carry it.
__version__ = "0.18.0.dev0"


def method_version(version: str = __version__) -> str:
    """The version of the method, ``major.minor`` of the package's version: runs of the same method
    version compute the same results (the trials' keys end with it)."""
    major, minor = version.split(".")[:2]
    return f"{major}.{minor}"
