"""Pictures of a run, optional and imported only when asked for: PNG plots of trajectories, errors,
particles and range images (``plots``, matplotlib) and the rerun viewer (``rerun``, the ``[viz]``
extra)."""
